"""Traffic-controller solve time on random tight-but-feasible instances.

Usage: python bench/solver_speed.py [--out bench/results/solver_speed.json] [--instances 5]
(without --out the table is printed and no file is written)

Instances are built feasible by construction: every GPU is filled towards its limit
with 1-3 of the models it hosts (r_ij = floor(share * C_i)), and N_i is the row sum. The
rounding down costs up to one robot per model and GPU, so with limits of 2-12 a GPU runs
at 14-100% of its limit (mean about 82% over the fixed seeds; the demand is 64-94% of the
cluster's capacity). Two placements per size:
``full`` (every model on every GPU) and ``partial`` (each model on a random subset of
GPUs, every GPU hosting at least one model). Seeds are fixed.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import random
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services.controlplane.solver import DEFAULT_TIME_LIMIT_S, PlanProblem, make_problem, solve  # noqa: E402

SIZES = [(8, 4), (16, 8), (32, 16)]  # (models, GPUs)
TARGETS_S = {(8, 4): 1.0, (32, 16): 10.0}


def make_instance(n_models: int, n_gpus: int, placement: str, seed: int) -> PlanProblem:
    rng = random.Random(seed)
    limits = [rng.randint(2, 12) for _ in range(n_models)]
    if placement == "full":
        hosts = [list(range(n_gpus)) for _ in range(n_models)]
    else:
        hosts = [sorted(rng.sample(range(n_gpus), rng.randint(1, max(1, n_gpus // 2)))) for _ in range(n_models)]
        for j in range(n_gpus):  # no idle GPU: give it a random model
            if not any(j in h for h in hosts):
                i = rng.randrange(n_models)
                hosts[i] = sorted(hosts[i] + [j])
    robots = [0] * n_models
    for j in range(n_gpus):
        here = [i for i in range(n_models) if j in hosts[i]]
        k = min(len(here), rng.randint(1, 3))
        # Models still without robots first, so nearly every model gets a population.
        rng.shuffle(here)
        here.sort(key=lambda i: robots[i] > 0)
        picked = here[:k]
        weights = [rng.random() + 0.2 for _ in picked]
        total = sum(weights)
        for i, w in zip(picked, weights):
            robots[i] += int(w / total * limits[i])
    return make_problem(
        n_gpus, [(f"m{i}", limits[i], robots[i], hosts[i]) for i in range(n_models)]
    )


def pct(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(q * (len(xs) - 1))))]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", help="JSON results file (default: none; the table is printed either way)")
    ap.add_argument("--instances", type=int, default=5, help="random instances per size and placement")
    ap.add_argument("--time-limit", type=float, default=DEFAULT_TIME_LIMIT_S, help="CP-SAT time limit per solve, seconds")
    ap.add_argument("--workers", type=int, default=None, help="CP-SAT workers (default: 1, repeatable plans; more race in parallel and are not deterministic)")
    args = ap.parse_args(argv)
    if args.instances < 1:
        ap.error(f"--instances: expected at least 1, got {args.instances}")
    if not args.time_limit > 0:
        ap.error(f"--time-limit: expected a positive number of seconds, got {args.time_limit}")
    if args.workers is not None and args.workers < 1:
        ap.error(f"--workers: expected at least 1, got {args.workers}")

    # Warm-up: the first solve pays for loading OR-Tools' native library.
    solve(make_problem(2, [("A", 4, 6, None), ("B", 4, 2, None)]))

    rows, runs = [], []
    for n_models, n_gpus in SIZES:
        for placement in ("full", "partial"):
            times, n_opt = [], 0
            for k in range(args.instances):
                seed = 1000 * n_models + 10 * n_gpus + k + (500 if placement == "partial" else 0)
                prob = make_instance(n_models, n_gpus, placement, seed)
                t0 = time.perf_counter()
                res = solve(prob, "ip", time_limit_s=args.time_limit, num_workers=args.workers)
                dt = time.perf_counter() - t0
                times.append(dt)
                n_opt += res.optimal
                runs.append(
                    {
                        "models": n_models, "gpus": n_gpus, "placement": placement, "seed": seed,
                        "robots": sum(m.robots for m in prob.models), "status": res.status,
                        "optimal": res.optimal, "objective": res.objective, "best_bound": res.best_bound,
                        "solve_s": round(dt, 4),
                        "smg_objective": solve(prob, "smg").objective,
                        "eps_objective": solve(prob, "eps").objective,
                        "max_gpu_load": round(float(max(res.gpu_load)), 3) if res.gpu_load else None,
                    }
                )
            rows.append(
                {
                    "models": n_models, "gpus": n_gpus, "placement": placement, "instances": len(times),
                    "median_s": round(statistics.median(times), 4), "p99_s": round(pct(times, 0.99), 4),
                    "max_s": round(max(times), 4), "proven_optimal": f"{n_opt}/{len(times)}",
                    "target_s": TARGETS_S.get((n_models, n_gpus)),
                }
            )
    try:
        commit = subprocess.check_output(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, text=True).strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    cpu = "unknown"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    out = {
        "command": "python " + " ".join([os.path.relpath(__file__, ROOT)] + (argv if argv is not None else sys.argv[1:])),
        "commit": commit, "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
        "time_limit_s": args.time_limit, "summary": rows, "runs": runs,
    }
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=2) + "\n")

    print(f"{'size':>8} {'placement':>9} {'n':>3} {'median_s':>9} {'p99_s':>7} {'max_s':>7} {'optimal':>8} {'target':>7}")
    for r in rows:
        tgt = f"<{r['target_s']:g}s" if r["target_s"] else "-"
        print(
            f"{r['models']:>3}x{r['gpus']:<4} {r['placement']:>9} {r['instances']:>3} {r['median_s']:>9.3f} "
            f"{r['p99_s']:>7.3f} {r['max_s']:>7.3f} {r['proven_optimal']:>8} {tgt:>7}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
