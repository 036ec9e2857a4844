#!/usr/bin/env bash
# E1's process-disaggregated counts rose between runs although that engine did not change (docs/RESULTS.md,
# "E1 again, all three engines"). This runs one sweep of it through the capacity harness as it was before commit
# 0456cee (reply times from the engine's stamp, 1 s drain) and through the current one, one after the other on the
# same GPU, and prints SLO attainment and p99 per count side by side.
#   OUT=dir [OLD=04add29] [MODEL=smolvla] [SWEEP=20,30,40,49] [ORDER="old new"] bash bench/experiments/harness_ab.sh
set -euo pipefail
OLD=${OLD:-04add29}
MODEL=${MODEL:-smolvla}
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
TREE=$(mktemp -d)/old
git -C "$ROOT" worktree add -f --detach "$TREE" "$OLD" >/dev/null
ARGS=(--models "$MODEL" --engines procdisagg --size full --device cuda:0 --epochs "${EPOCHS:-3}" --duration 3
      --sweep "${SWEEP:-20,30,40,49}" --no-early-stop --quiet)
for which in ${ORDER:-old new}; do
  if [ "$which" = old ]; then
    (cd "$TREE" && PYTHONPATH="${SITE:-}:$TREE" python bench/capacity.py "${ARGS[@]}" --out "$OUT/harness_ab_$which.json")
  else
    (cd "$ROOT" && PYTHONPATH="${SITE:-}:$ROOT" python bench/capacity.py "${ARGS[@]}" --out "$OUT/harness_ab_$which.json")
  fi
done
git -C "$ROOT" worktree remove --force "$TREE"
python - "$OUT" "$MODEL" <<'PY'
import json, sys
out, model = sys.argv[1], sys.argv[2]
runs = {w: json.load(open(f"{out}/harness_ab_{w}.json"))["curves"][model]["procdisagg"] for w in ("old", "new")}
print(f"{'robots':>6} | {'old harness: SLO %, p99 ms':>28} | {'current harness: SLO %, p99 ms':>32}")
for n in sorted({p["robots"] for pts in runs.values() for p in pts}):
    cells = []
    for w in ("old", "new"):
        p = next((p for p in runs[w] if p["robots"] == n), None)
        cells.append(f"{100 * p['slo_attainment']:.1f}, {p['p99_ms']:.1f}" if p else "-")
    print(f"{n:>6} | {cells[0]:>28} | {cells[1]:>32}")
PY
