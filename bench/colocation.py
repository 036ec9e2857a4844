"""Co-location (paper experiment 4) and queue-policy (experiment 5) runs on one GPU.

E4: 2-4 models share one GPU (same or different architectures, balanced or skewed robot
populations); Robion and Monolithic serve the same seeded robots, side by side in one
process, and the SLO miss ratio (1 - SLO attainment) is compared.
E5: the Robion engine with earliest-SLO-first, round-robin and largest-queue-first queues,
with equal and with different deadlines.

    python bench/colocation.py e4 --size full --device cuda:0 --robots 12,16,20 --out bench/results/colocation_e4.json
    python bench/colocation.py e5 --size full --device cuda:0 --robots 12,16,20 --out bench/results/policies_e5.json
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # sibling bench modules (capacity)

from shared.config import ConfigError, engine_config  # noqa: E402
from shared.files import unwritable  # noqa: E402

PAPER_DEADLINES_MS = {"pi0": 156.0, "xr0": 117.0, "smolvla": 50.0, "groot_n15": 53.0}

# name -> [(model name, arch, seed, share of the robots)]
E4_SCENARIOS = {
    "same-2": [("pi0-a", "pi0", 1, 1), ("pi0-b", "pi0", 2, 1)],
    "same-4": [("pi0-a", "pi0", 1, 1), ("pi0-b", "pi0", 2, 1), ("pi0-c", "pi0", 3, 1), ("pi0-d", "pi0", 4, 1)],
    "diff-2": [("pi0", "pi0", 1, 1), ("xr0", "xr0", 1, 1)],
    "diff-4": [("pi0", "pi0", 1, 1), ("xr0", "xr0", 1, 1), ("smolvla", "smolvla", 1, 1), ("groot", "groot_n15", 1, 1)],
    "skewed-2": [("pi0", "pi0", 1, 3), ("xr0", "xr0", 1, 1)],
    "skewed-same-2": [("pi0-a", "pi0", 1, 3), ("pi0-b", "pi0", 2, 1)],
}
# E5: (scenario, deadline override per model in ms or None for the paper's)
E5_SCENARIOS = {
    "equal-deadlines": ([("pi0", "pi0", 1, 1), ("xr0", "xr0", 1, 1)], {"pi0": 117.0, "xr0": 117.0}),
    "different-deadlines": ([("pi0", "pi0", 1, 1), ("xr0", "xr0", 1, 1), ("smolvla", "smolvla", 1, 1)], {}),
}


def split(total: int, shares: list[float]) -> list[int]:
    """Integer robot counts in proportion to ``shares`` summing to ``total`` (largest remainders)."""
    raw = [total * s / sum(shares) for s in shares]
    out = [int(x) for x in raw]
    for i in sorted(range(len(raw)), key=lambda i: raw[i] - out[i], reverse=True)[: total - sum(out)]:
        out[i] += 1
    return out


def run(args) -> dict:
    import torch

    from services.executor.engine import ServedModel
    from services.executor.simulation import EngineHost, RobotGroup, SimConfig, engine_factory, simulate
    from shared.models import build_model

    device = args.device
    sim = SimConfig(epochs=args.epochs, duration_s=args.duration, seed=args.seed)
    if args.experiment == "e4":
        scenarios = {n: (s, {}) for n, s in E4_SCENARIOS.items() if not args.scenarios or n in args.scenarios}
        engines = {"robion": {"kind": "robion"}, "monolithic": {"kind": "monolithic"}}
        if args.shed_late:
            engines["robion-shed"] = {"kind": "robion", "shed_late": True}
    else:
        scenarios = {n: s for n, s in E5_SCENARIOS.items() if not args.scenarios or n in args.scenarios}
        engines = {p: {"kind": "robion", "policy": p} for p in ("esf", "rr", "lqf")}
        if args.shed_late:  # ESF that also sheds requests that can no longer make their deadline
            engines["esf-shed"] = {"kind": "robion", "policy": "esf", "shed_late": True}
    common = {"max_batch": args.max_batch}
    if args.sm_table:
        common["sm_table"] = args.sm_table
    cache: dict = {}
    rows = []
    for name, (models, deadlines) in scenarios.items():
        served = {}
        for mname, arch, seed, _ in models:
            key = (arch, seed)
            if key not in cache:
                cache[key] = build_model(arch, args.size, seed=seed, device=device)
            ms = deadlines.get(mname, PAPER_DEADLINES_MS.get(arch, args.deadline))
            served[mname] = ServedModel(mname, cache[key], ms / 1e3)
        hosts = {label: EngineHost(engine_factory(e["kind"], served, device, **common,
                                                  **{k: v for k, v in e.items() if k != "kind"}), label=label)
                 for label, e in engines.items()}
        for i, total in enumerate(args.robots):
            counts = split(total, [m[3] for m in models])
            workload = [RobotGroup(m[0], n, args.hz) for m, n in zip(models, counts) if n > 0]
            # Alternate who runs first from one count to the next (by the count's parity it never did: every
            # documented sweep is of even counts).
            labels = list(hosts) if i % 2 == 0 else list(reversed(hosts))
            for label in labels:
                res = simulate(hosts[label], workload, sim)
                rows.append({"scenario": name, "engine": label, "robots": total, "counts": counts,
                             "slo_attainment": res.overall.slo_attainment, "miss_ratio": 1 - res.overall.slo_attainment,
                             "p99_ms": res.overall.p99_ms, "submit_lag_max_ms": res.submit_lag_max_ms,
                             "models": {m: {"slo_attainment": s.slo_attainment, "p99_ms": s.p99_ms}
                                        for m, s in res.models.items()},
                             "deadlines_ms": res.deadlines_ms})
                print(f"{name:<20}{label:<12}{total:>4} robots  SLO-AT {100 * res.overall.slo_attainment:6.1f}%  "
                      f"p99 {res.overall.p99_ms:7.1f} ms", flush=True)
        for h in hosts.values():
            h.close()
    from capacity import dirty, source_commit

    commit = source_commit(short=True) or ""
    meta = {"experiment": args.experiment, "date": datetime.date.today().isoformat(), "commit": commit, "dirty": dirty(),
            "device": torch.cuda.get_device_name(torch.device(device)) if device.startswith("cuda") else "cpu",
            "torch": torch.__version__,
            "size": args.size, "hz": args.hz, "epochs": args.epochs, "duration_s": args.duration,
            "command": "python bench/colocation.py " + " ".join(sys.argv[1:])}
    return {"meta": meta, "rows": rows, "summary": summary(rows, args.experiment)}


def summary(rows: list[dict], experiment: str) -> dict:
    """E4: mean SLO miss ratio per engine and Monolithic / Robion; E5: mean SLO attainment per policy."""
    by_engine: dict[str, list[float]] = {}
    for r in rows:
        by_engine.setdefault(r["engine"], []).append(r["miss_ratio"] if experiment == "e4" else r["slo_attainment"])
    means = {e: sum(v) / len(v) for e, v in by_engine.items()}

    def ratio(a: str, b: str) -> float | None:
        """means[a] / means[b]; None (null) where it is undefined: an engine missing, or b at 0 (Robion
        missing nothing), which no finite ratio describes. JSON has no Infinity."""
        return means[a] / means[b] if a in means and means.get(b) else None

    if experiment == "e4":
        return {"mean_miss_ratio": means, "monolithic_over_robion": ratio("monolithic", "robion")}
    return {"mean_slo_attainment": means, "esf_over_rr": ratio("esf", "rr"), "esf_over_lqf": ratio("esf", "lqf")}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("experiment", choices=["e4", "e5"])
    p.add_argument("--scenarios", nargs="*", help="subset of the built-in scenarios (e4: "
                   f"{', '.join(E4_SCENARIOS)}; e5: {', '.join(E5_SCENARIOS)}; default: all)")
    p.add_argument("--size", default="full")
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--robots", default="12,16,20", help="total robots on the GPU, split by the scenario's shares")
    p.add_argument("--hz", type=float, default=2.0)
    p.add_argument("--max-batch", type=int, default=2)
    p.add_argument("--sm-table", default=None)
    p.add_argument("--epochs", type=int, default=5)
    p.add_argument("--duration", type=float, default=10.0)
    p.add_argument("--deadline", type=float, default=156.0, help="deadline for architectures the paper has none for")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--shed-late", action="store_true",
                   help="also run Robion (ESF) with engine.shed_late: requests that cannot finish in time are shed")
    p.add_argument("--out", default="")
    args = p.parse_args(argv)
    known = E4_SCENARIOS if args.experiment == "e4" else E5_SCENARIOS
    unknown = sorted(set(args.scenarios or ()) - set(known))
    if unknown:  # they used to be skipped, and an empty result written with exit 0
        p.error(f"--scenarios: {args.experiment} has no scenario {', '.join(unknown)} (it has {', '.join(known)})")
    try:
        args.robots = [int(x) for x in args.robots.split(",") if x.strip()]
    except ValueError:
        args.robots = []
    if not args.robots or min(args.robots) < 1:  # a 0-robot row's NaN attainment turned every mean into null
        p.error("--robots: expected comma-separated robot counts of at least 1")
    # Checked before any model is built: a max_batch of 0 ran to 0% attainment, 3 ran although a config refuses it.
    try:
        engine_config({"kind": "robion", "max_batch": args.max_batch})
    except ConfigError as exc:
        p.error(f"--max-batch: {exc}")
    for name, value in (("--hz", args.hz), ("--duration", args.duration), ("--deadline", args.deadline)):
        if not (math.isfinite(value) and value > 0):
            p.error(f"{name}: expected a positive number, got {value}")
    if args.duration < 1 / args.hz:
        # Shorter, and a robot whose random start falls after the window sends nothing: a model of few robots then
        # sent nothing in some epochs, and its row averaged the others (as bench/capacity.py refuses).
        p.error(f"--duration: expected at least one period (1 / --hz = {1 / args.hz:g} s), got {args.duration}")
    if args.epochs < 1:
        p.error(f"--epochs: expected at least 1, got {args.epochs}")
    if args.out and (why := unwritable(args.out)):  # before the run, not after it
        p.error(f"--out: {why}")
    t0 = time.monotonic()
    result = run(args)
    result["meta"]["wall_s"] = round(time.monotonic() - t0, 1)
    from services.executor.simulation import _json_safe

    if args.out:
        with open(args.out, "w") as fh:
            # NaN (an empty workload's attainment) is no JSON either: null, and strict parsers read the file.
            json.dump(_json_safe(result), fh, indent=2, allow_nan=False)
    print(json.dumps(_json_safe(result["summary"]), indent=1, allow_nan=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
