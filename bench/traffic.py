"""Multi-GPU management experiments (paper experiments 6 and 7): traffic strategies and placements.

Robots are pinned to GPUs by the assignment, so each GPU serves its own robots independently:
every GPU's workload is simulated through its own engine (services/executor/simulation.py),
on several GPUs at once (--devices cuda:0,cuda:1,...) or one after another on one GPU. The
router hop, measured separately (docs/RESULTS.md), is not part of these numbers.

    # experiment 6: 4 fine-tuned variants at 1/2/2/4 Hz on 4 GPUs, SMG vs EPS vs the integer program
    python bench/traffic.py strategies --arch pi0 --size full --gpus 4 --devices cuda:0 --out bench/results/traffic_strategies.json
    # experiment 7: 4 + 4 variants of two architectures, Mix vs disjoint groups, over total robot counts
    python bench/traffic.py placements --arch pi0 --arch2 xr0 --size full --gpus 4 --robots 32,48,64 --devices cuda:0 --out ...
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import datetime
import json
import multiprocessing as mp
import os
import sys
import time
from dataclasses import dataclass, field

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # sibling bench modules (capacity)

from services.controlplane.solver import ModelDemand, PlanProblem, solve  # noqa: E402

PAPER_DEADLINES_MS = {"pi0": 156.0, "xr0": 117.0, "smolvla": 50.0, "groot_n15": 53.0}


@dataclass
class Variant:
    name: str
    arch: str
    seed: int
    hz: float
    slo_ms: float
    robots: int = 0
    limit: int = 0
    gpus: tuple[int, ...] = ()


@dataclass
class GpuJob:
    """One GPU's share of an assignment: the models it serves and their robots."""

    label: str
    gpu: int
    size: str
    engine: dict
    sim: dict
    models: list[Variant] = field(default_factory=list)
    robots: dict[str, int] = field(default_factory=dict)


# ----------------------------------------------------------------------------- per-GPU simulation

_MODELS: dict[tuple, object] = {}


def _model(arch: str, size: str, seed: int, device: str):
    from shared.models import build_model

    key = (arch, size, seed, device)
    if key not in _MODELS:
        _MODELS[key] = build_model(arch, size, seed=seed, device=device)
    return _MODELS[key]


def run_gpu(job: GpuJob, device: str) -> dict:
    """Simulate one GPU's assigned robots through an engine serving just its models."""
    import torch

    from services.executor.engine import ServedModel
    from services.executor.simulation import RobotGroup, SimConfig, engine_factory, simulate

    if device.startswith("cuda"):
        torch.cuda.set_device(torch.device(device))
    active = [v for v in job.models if job.robots.get(v.name, 0) > 0]
    if not active:
        return {"label": job.label, "gpu": job.gpu, "sent": 0, "met": 0, "models": {}}
    served = {v.name: ServedModel(v.name, _model(v.arch, job.size, v.seed, device), v.slo_ms / 1e3) for v in active}
    workload = [RobotGroup(v.name, job.robots[v.name], v.hz) for v in active]
    result = simulate(engine_factory(job.engine["kind"], served, device, **{k: x for k, x in job.engine.items() if k != "kind"}),
                      workload, SimConfig(**job.sim))
    return {"label": job.label, "gpu": job.gpu, "sent": result.overall.sent, "met": result.overall.met,
            "slo_attainment": result.overall.slo_attainment, "submit_lag_max_ms": result.submit_lag_max_ms,
            "models": {m: {"robots": job.robots[m], "sent": s.sent, "met": s.met, "slo_attainment": s.slo_attainment,
                           "p99_ms": s.p99_ms} for m, s in result.models.items()}}


def run_jobs(jobs: list[GpuJob], devices: list[str]) -> list[dict]:
    """Jobs on several devices at once (one process each), or in this process on one device."""
    if len(devices) == 1:
        return [run_gpu(job, devices[0]) for job in jobs]
    ctx = mp.get_context("spawn")
    out: list[dict] = []
    with cf.ProcessPoolExecutor(max_workers=len(devices), mp_context=ctx) as pool:
        for start in range(0, len(jobs), len(devices)):
            wave = jobs[start:start + len(devices)]
            out.extend(pool.map(run_gpu, wave, devices[:len(wave)]))
    return out


# ----------------------------------------------------------------------------- limits and assignments

def measure_limit(v: Variant, size: str, device: str, engine: dict, sim: dict, target: float, max_robots: int,
                  cache: dict) -> int:
    """C_i of a variant at its rate (cached per architecture and rate: variants share it)."""
    from services.executor.engine import ServedModel
    from services.executor.simulation import SimConfig, engine_factory, find_capacity

    key = (v.arch, v.hz, v.slo_ms)
    if key not in cache:
        served = {v.name: ServedModel(v.name, _model(v.arch, size, v.seed, device), v.slo_ms / 1e3)}
        # Screened search (one-epoch bracketing, full runs on the candidate): the limits are
        # most of this experiment's GPU time otherwise.
        res = find_capacity(engine_factory(engine["kind"], served, device, **{k: x for k, x in engine.items() if k != "kind"}),
                            v.name, hz=v.hz, sim=SimConfig(**sim), target=target, start=min(8, max_robots),
                            max_robots=max_robots, screen_epochs=1)
        cache[key] = max(1, res.capacity)
    return cache[key]


def assignment(variants: list[Variant], gpus: int, strategy: str) -> tuple[dict[str, dict[int, int]], dict]:
    problem = PlanProblem(gpus, tuple(ModelDemand(v.name, v.limit, v.robots, v.gpus) for v in variants))
    res = solve(problem, strategy)
    if not res.assignment and strategy == "ip":  # infeasible: what the control plane does, split evenly
        res = solve(problem, "eps")
    return res.assignment, {"strategy": res.strategy, "objective": res.objective, "feasible": res.feasible,
                            "optimal": res.optimal, "gpu_load": [float(x) for x in res.gpu_load]}


def jobs_for(label: str, variants: list[Variant], assign: dict[str, dict[int, int]], gpus: int, size: str,
             engine: dict, sim: dict) -> list[GpuJob]:
    jobs = []
    for j in range(gpus):
        robots = {v.name: assign.get(v.name, {}).get(j, 0) for v in variants}
        hosted = [v for v in variants if j in v.gpus]
        jobs.append(GpuJob(label, j, size, engine, sim, hosted, robots))
    return jobs


def summarize(label: str, results: list[dict], extra: dict) -> dict:
    sent = sum(r["sent"] for r in results)
    met = sum(r["met"] for r in results)
    return {"label": label, "sent": sent, "misses": sent - met, "slo_attainment": met / sent if sent else float("nan"),
            "gpus": results, **extra}


# ----------------------------------------------------------------------------- experiments

def populations(variants: list[Variant], gpus: int, load: float, shares: list[float]) -> None:
    """N_i so the variants together ask for ``load`` x ``gpus`` GPU-equivalents, split by ``shares``."""
    total = sum(shares)
    for v, s in zip(variants, shares):
        v.robots = max(1, round(load * gpus * s / total * v.limit))


def exp_strategies(args, engine: dict, sim: dict, limit_sim: dict, devices: list[str]) -> dict:
    rates = [float(x) for x in args.rates.split(",")]
    variants = [Variant(f"{args.arch}-ft{i}", args.arch, i + 1, hz, args.deadline or PAPER_DEADLINES_MS[args.arch],
                        gpus=tuple(range(args.gpus))) for i, hz in enumerate(rates)]
    cache: dict = {}
    t0 = time.monotonic()
    for v in variants:
        v.limit = measure_limit(v, args.size, devices[0], engine, limit_sim, args.target, args.max_robots, cache)
    limits_s = time.monotonic() - t0
    populations(variants, args.gpus, args.load, [float(x) for x in args.shares.split(",")])
    rows = []
    for strategy in ("smg", "eps", "ip"):
        assign, info = assignment(variants, args.gpus, strategy)
        results = run_jobs(jobs_for(strategy, variants, assign, args.gpus, args.size, engine, sim), devices)
        rows.append(summarize(strategy, results, {"assignment": assign, **info}))
    ip = next(r for r in rows if r["label"] == "ip")
    for r in rows:
        r["misses_vs_ip"] = r["misses"] / ip["misses"] if ip["misses"] else (float("inf") if r["misses"] else 1.0)
    return {"variants": [v.__dict__ for v in variants], "limits_s": limits_s, "rows": rows}


def exp_placements(args, engine: dict, sim: dict, limit_sim: dict, devices: list[str]) -> dict:
    archs = [args.arch, args.arch2]
    variants = [Variant(f"{a}-ft{i}", a, i + 1, args.hz, PAPER_DEADLINES_MS[a]) for a in archs for i in range(4)]
    cache: dict = {}
    for v in variants:
        v.limit = measure_limit(v, args.size, devices[0], engine, limit_sim, args.target, args.max_robots, cache)
    g = args.gpus
    placements = {"mix": {a: tuple(range(g)) for a in archs}}
    for k in range(1, g):
        placements[f"gr-{k}:{g - k}"] = {archs[0]: tuple(range(k)), archs[1]: tuple(range(k, g))}
    rows = []
    for total in [int(x) for x in args.robots.split(",")]:
        for label, hosts in placements.items():
            for i, v in enumerate(variants):
                v.gpus = hosts[v.arch]
                v.robots = total // len(variants) + (1 if i < total % len(variants) else 0)
            assign, info = assignment(variants, g, "ip")
            results = run_jobs(jobs_for(label, variants, assign, g, args.size, engine, sim), devices)
            rows.append(summarize(label, results, {"robots": total, "assignment": assign, **info}))
    return {"variants": [{**v.__dict__, "gpus": None} for v in variants], "rows": rows}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("experiment", choices=["strategies", "placements"])
    p.add_argument("--arch", default="pi0")
    p.add_argument("--arch2", default="xr0")
    p.add_argument("--size", default="full")
    p.add_argument("--gpus", type=int, default=4, help="GPUs of the modelled server")
    p.add_argument("--devices", default="cuda:0", help="devices to simulate on, comma-separated")
    p.add_argument("--engine", default="robion")
    p.add_argument("--max-batch", type=int, default=2)
    p.add_argument("--sm-table", default=None)
    p.add_argument("--rates", default="1,2,2,4", help="strategies: request rate of each variant")
    p.add_argument("--shares", default="1,1,1,1", help="strategies: share of the load of each variant")
    p.add_argument("--load", type=float, default=0.9, help="strategies: demand as a share of total GPU capacity")
    p.add_argument("--hz", type=float, default=2.0, help="placements: request rate")
    p.add_argument("--robots", default="32,48,64", help="placements: total robot counts")
    p.add_argument("--deadline", type=float, default=0.0, help="deadline in ms (default: the paper's for --arch)")
    p.add_argument("--target", type=float, default=0.98)
    p.add_argument("--max-robots", type=int, default=256, help="limit search: most robots per GPU")
    p.add_argument("--epochs", type=int, default=3)
    p.add_argument("--duration", type=float, default=10.0)
    p.add_argument("--limit-epochs", type=int, default=2)
    p.add_argument("--limit-duration", type=float, default=5.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="")
    args = p.parse_args(argv)
    if args.deadline:
        PAPER_DEADLINES_MS.setdefault(args.arch, args.deadline)
    devices = args.devices.split(",")
    engine = {"kind": args.engine, "max_batch": args.max_batch}
    if args.sm_table:
        engine["sm_table"] = args.sm_table
    sim = {"epochs": args.epochs, "duration_s": args.duration, "seed": args.seed}
    limit_sim = {"epochs": args.limit_epochs, "duration_s": args.limit_duration, "seed": args.seed}
    t0 = time.monotonic()
    run = exp_strategies if args.experiment == "strategies" else exp_placements
    result = run(args, engine, sim, limit_sim, devices)
    import torch

    from capacity import source_commit

    commit = source_commit(short=True) or ""
    result["meta"] = {"experiment": args.experiment, "date": datetime.date.today().isoformat(), "commit": commit,
                      "device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu",
                      "devices": devices, "torch": torch.__version__, "wall_s": round(time.monotonic() - t0, 1),
                      "command": "python bench/traffic.py " + " ".join(sys.argv[1:] if argv is None else argv)}
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(result, fh, indent=2, default=str)
    print(f"{'run':<12}{'robots':>7}{'sent':>8}{'misses':>8}{'SLO-AT':>9}{'vs IP':>8}  assignment")
    for r in result["rows"]:
        robots = r.get("robots", sum(v["robots"] for v in result["variants"]))
        print(f"{r['label']:<12}{robots:>7}{r['sent']:>8}{r['misses']:>8}{100 * r['slo_attainment']:>8.1f}%"
              f"{r.get('misses_vs_ip', float('nan')):>8.2f}  {r['assignment']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
