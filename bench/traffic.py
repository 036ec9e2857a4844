"""Multi-GPU management experiments (paper experiments 6 and 7): traffic strategies and placements.

Robots are pinned to GPUs by the assignment, so each GPU serves its own robots independently:
every GPU's workload is simulated through its own engine (services/executor/simulation.py),
on several GPUs at once (--devices cuda:0,cuda:1,...) or one after another on one GPU. The
router hop, measured separately (docs/RESULTS.md), is not part of these numbers.

    # the robot limits both experiments need, measured on all devices at once into a cache file
    python bench/traffic.py limits --arch pi0 --arch2 xr0 --rates 1,2,4 --hz 2 --devices cuda:0,cuda:1,cuda:2,cuda:3 \\
        --limits-cache bench/results/traffic_limits.json
    # experiment 6: 4 fine-tuned variants at 1/2/2/4 Hz, equal robots, 90% of 4 GPUs; SMG vs EPS vs the integer program
    python bench/traffic.py strategies --arch pi0 --devices cuda:0,cuda:1,cuda:2,cuda:3 \\
        --limits-cache bench/results/traffic_limits.json --out bench/results/traffic_strategies.json
    # experiment 7: 4 + 4 variants of two architectures, Mix vs disjoint groups, at shares of the GPUs' capacity
    python bench/traffic.py placements --arch pi0 --arch2 xr0 --loads 0.8,0.9,1.0 --devices cuda:0,cuda:1,cuda:2,cuda:3 \\
        --limits-cache bench/results/traffic_limits.json --out bench/results/traffic_placements.json
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
from shared.config import ConfigError, engine_config  # noqa: E402
from shared.files import unwritable  # noqa: E402

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


_HOST: dict[tuple, object] = {}  # this worker's prepared engine, keyed by what it serves


def release_engine(keep: frozenset = frozenset()) -> None:
    """Close this worker's engine and drop the weights not in ``keep`` (GPU memory back for the
    next models; weights the next engine uses again are kept)."""
    for host in _HOST.values():
        host.close()
    _HOST.clear()
    for key in set(_MODELS) - keep:
        del _MODELS[key]


def _host(models: list[Variant], size: str, engine: dict, device: str, label: str):
    """An engine (not yet prepared) serving ``models`` on ``device``, weights from this worker's cache."""
    from services.executor.engine import ServedModel
    from services.executor.simulation import EngineHost, engine_factory

    served = {v.name: ServedModel(v.name, _model(v.arch, size, v.seed, device), v.slo_ms / 1e3) for v in models}
    return EngineHost(engine_factory(engine["kind"], served, device, **{k: x for k, x in engine.items() if k != "kind"}),
                      label=label)


def _engine_host(job: GpuJob, device: str):
    """The prepared engine for the models this GPU hosts, reused while the next job on this
    device hosts the same ones: with a device per modelled GPU, graph capture and profiling
    happen once per placement, not once per run. One engine at a time per worker."""
    key = (device, tuple(v.name for v in job.models), tuple(sorted(job.engine.items())))
    if key not in _HOST:
        release_engine(frozenset((v.arch, job.size, v.seed, device) for v in job.models))
        _HOST[key] = _host(job.models, job.size, job.engine, device, f"gpu{job.gpu}")
    return _HOST[key]


def run_gpu(job: GpuJob, device: str) -> dict:
    """Simulate one GPU's assigned robots through an engine serving the models it hosts."""
    from services.executor.simulation import RobotGroup, SimConfig, simulate

    active = [v for v in job.models if job.robots.get(v.name, 0) > 0]
    if not active:
        return {"label": job.label, "gpu": job.gpu, "sent": 0, "met": 0, "models": {}}
    workload = [RobotGroup(v.name, job.robots[v.name], v.hz) for v in active]
    result = simulate(_engine_host(job, device), workload, SimConfig(**job.sim))
    return {"label": job.label, "gpu": job.gpu, "sent": result.overall.sent, "met": result.overall.met,
            "slo_attainment": result.overall.slo_attainment, "submit_lag_max_ms": result.submit_lag_max_ms,
            "models": {m: {"robots": job.robots[m], "sent": s.sent, "met": s.met, "slo_attainment": s.slo_attainment,
                           "p99_ms": s.p99_ms} for m, s in result.models.items()}}


def bind_device(device: str) -> None:
    """Make ``device`` current for this process (its workers run everything on it)."""
    if device.startswith("cuda"):
        import torch

        torch.cuda.set_device(torch.device(device))


class DevicePool:
    """One worker process per device, kept for the whole experiment, so each device builds its
    models once (a shared pool would move jobs between devices and keep several copies of the
    weights on one GPU). With one device everything runs in this process, one job after another."""

    def __init__(self, devices: list[str]):
        self.devices = devices
        ctx = mp.get_context("spawn")
        self._pools = ([cf.ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=bind_device, initargs=(d,))
                        for d in devices] if len(devices) > 1 else [])
        if not self._pools:
            bind_device(devices[0])

    def run(self, calls: list[tuple[int, object, tuple]]) -> list:
        """``(slot, fn, args)`` calls, each on device ``slot % len(devices)`` (as ``fn(*args, device)``);
        calls on different devices run at once. Results in call order; the first failure is raised."""
        if not self._pools:
            return [fn(*args, self.devices[0]) for _, fn, args in calls]
        futures = [self._pools[slot % len(self._pools)].submit(fn, *args, self.devices[slot % len(self.devices)])
                   for slot, fn, args in calls]
        try:
            return [f.result() for f in futures]
        except BaseException:
            for f in futures:
                f.cancel()
            raise

    def close(self) -> None:
        if not self._pools:
            release_engine()
        for pool in self._pools:
            pool.shutdown(cancel_futures=True)


def run_jobs(jobs: list[GpuJob], pool: DevicePool) -> list[dict]:
    """Each GPU's job on device ``gpu % devices``: the GPUs of the modelled server run at once
    when there are as many devices, one after another otherwise."""
    return pool.run([(job.gpu, run_gpu, (job,)) for job in jobs])


# ----------------------------------------------------------------------------- limits and assignments

def measure_limit(v: Variant, size: str, engine: dict, sim: dict, target: float, start: int, max_robots: int,
                  device: str) -> int:
    """C_i of a variant at its rate on ``device``: the screened capacity search of one engine
    serving only this variant (one-epoch bracketing, full runs on the candidate)."""
    from services.executor.simulation import SimConfig, find_capacity

    host = _host([v], size, engine, device, f"limit {v.arch} {v.hz:g} Hz")
    try:
        res = find_capacity(host, v.name, hz=v.hz, sim=SimConfig(**sim), target=target, start=min(start, max_robots),
                            max_robots=max_robots, screen_epochs=1, progress=False)
    finally:
        host.close()  # graphs and buffers freed before the experiment's engines are built
    return max(1, res.capacity)


def measure_limits(variants: list[Variant], args, engine: dict, limit_sim: dict, pool: DevicePool, gpu: str) -> float:
    """Fill ``limit`` of every variant from the cache file, measuring the missing ones (keyed by architecture,
    rate, deadline and engine settings) on all devices at once; returns the seconds spent measuring."""
    from services.executor.limits import LimitCache, limit_key

    cache = LimitCache(args.limits_cache) if args.limits_cache else None
    known = {k: e["limit"] for k, e in (cache.read() if cache else {}).items()}
    keys = [limit_key(gpu, v.arch, args.size, v.hz, engine["max_batch"], v.slo_ms, engine["kind"], args.target)
            for v in variants]
    missing: dict[str, Variant] = {}
    for key, v in zip(keys, variants):
        if key not in known:
            missing.setdefault(key, v)
    t0 = time.monotonic()
    if missing:
        print(f"measuring {len(missing)} robot limits on {len(pool.devices)} device(s): "
              + ", ".join(f"{v.arch} at {v.hz:g} Hz" for v in missing.values()), flush=True)
        found = pool.run([(i, measure_limit, (v, args.size, engine, limit_sim, args.target, args.limit_start,
                                               args.max_robots)) for i, v in enumerate(missing.values())])
        for key, limit in zip(missing, found):
            known[key] = limit
            if cache:
                cache.write(key, {"limit": limit, "sim": limit_sim, "date": datetime.date.today().isoformat()})
    for key, v in zip(keys, variants):
        v.limit = known[key]
    return time.monotonic() - t0


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
    """Robots N_i in proportion to ``shares``, scaled so that together they ask for ``load`` x
    ``gpus`` GPU-equivalents (N_i / C_i summed). Equal shares at different rates is the paper's
    case: the fast variant needs more GPU than the slow ones for the same robots."""
    scale = load * gpus / sum(s / v.limit for v, s in zip(variants, shares))
    for v, s in zip(variants, shares):
        v.robots = max(1, round(s * scale))


def exp_strategies(args, engine: dict, sim: dict, limit_sim: dict, pool: DevicePool, gpu: str) -> dict:
    rates = [float(x) for x in args.rates.split(",")]
    variants = [Variant(f"{args.arch}-ft{i}", args.arch, i + 1, hz, args.deadline or PAPER_DEADLINES_MS[args.arch],
                        gpus=tuple(range(args.gpus))) for i, hz in enumerate(rates)]
    limits_s = measure_limits(variants, args, engine, limit_sim, pool, gpu)
    populations(variants, args.gpus, args.load, [float(x) for x in args.shares.split(",")])
    rows = []
    for strategy in ("smg", "eps", "ip"):
        assign, info = assignment(variants, args.gpus, strategy)
        print(f"running {strategy}: {assign}", flush=True)
        results = run_jobs(jobs_for(strategy, variants, assign, args.gpus, args.size, engine, sim), pool)
        rows.append(summarize(strategy, results, {"assignment": assign, **info}))
    ip = next(r for r in rows if r["label"] == "ip")
    for r in rows:
        r["misses_vs_ip"] = r["misses"] / ip["misses"] if ip["misses"] else (float("inf") if r["misses"] else 1.0)
    return {"variants": [v.__dict__ for v in variants], "limits_s": limits_s, "rows": rows}


def placement_variants(args) -> list[Variant]:
    # --deadline is --arch's (its help says so); it used to be ignored here for an architecture with a paper deadline.
    def deadline(arch: str) -> float:
        return (args.deadline if arch == args.arch else 0.0) or PAPER_DEADLINES_MS[arch]

    return [Variant(f"{a}-ft{i}", a, i + 1, args.hz, deadline(a)) for a in (args.arch, args.arch2) for i in range(4)]


def exp_placements(args, engine: dict, sim: dict, limit_sim: dict, pool: DevicePool, gpu: str) -> dict:
    archs = [args.arch, args.arch2]
    variants = placement_variants(args)
    limits_s = measure_limits(variants, args, engine, limit_sim, pool, gpu)
    g = args.gpus
    if args.loads:
        # Equal populations: a total of N robots asks for N x mean(1 / C_i) GPU-equivalents.
        mean_inv = sum(1 / v.limit for v in variants) / len(variants)
        totals = [round(float(x) * g / mean_inv) for x in args.loads.split(",")]
    else:
        totals = [int(x) for x in args.robots.split(",")]
    placements = {"mix": {a: tuple(range(g)) for a in archs}}
    for k in range(1, g):
        placements[f"gr-{k}:{g - k}"] = {archs[0]: tuple(range(k)), archs[1]: tuple(range(k, g))}
    rows = []
    # Placement-major, so each GPU prepares the engine for its hosted models once per placement.
    for label, hosts in placements.items():
        for total in totals:
            for i, v in enumerate(variants):
                v.gpus = hosts[v.arch]
                v.robots = total // len(variants) + (1 if i < total % len(variants) else 0)
            assign, info = assignment(variants, g, "ip")
            print(f"running {label} with {total} robots: {assign}", flush=True)
            results = run_jobs(jobs_for(label, variants, assign, g, args.size, engine, sim), pool)
            rows.append(summarize(label, results, {"robots": total, "assignment": assign, **info}))
    return {"variants": [{**v.__dict__, "gpus": None} for v in variants], "limits_s": limits_s, "rows": rows}


def exp_limits(args, engine: dict, sim: dict, limit_sim: dict, pool: DevicePool, gpu: str) -> dict:
    """The limits both experiments need, measured at once into --limits-cache."""
    slo = args.deadline or PAPER_DEADLINES_MS[args.arch]
    variants = [Variant(f"{args.arch}@{x}", args.arch, 1, float(x), slo) for x in dict.fromkeys(args.rates.split(","))]
    variants += [v for v in placement_variants(args)[::4] if (v.arch, v.hz) not in {(x.arch, x.hz) for x in variants}]
    limits_s = measure_limits(variants, args, engine, limit_sim, pool, gpu)
    return {"variants": [v.__dict__ for v in variants], "limits_s": limits_s, "rows": []}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("experiment", choices=["strategies", "placements", "limits"],
                   help="limits: measure the limits both experiments need into --limits-cache, on all devices at once")
    p.add_argument("--arch", default="pi0")
    p.add_argument("--arch2", default="xr0")
    p.add_argument("--size", default="full")
    p.add_argument("--gpus", type=int, default=4, help="GPUs of the modelled server")
    p.add_argument("--devices", default="cuda:0", help="devices to simulate on, comma-separated")
    p.add_argument("--engine", default="robion")
    p.add_argument("--max-batch", type=int, default=2)
    p.add_argument("--sm-table", default=None)
    p.add_argument("--rates", default="1,2,2,4", help="strategies: request rate of each variant; limits: the "
                   "rates to measure --arch at")
    p.add_argument("--shares", default="1,1,1,1", help="strategies: share of the robots of each variant")
    p.add_argument("--load", type=float, default=0.9, help="strategies: demand as a share of total GPU capacity")
    p.add_argument("--hz", type=float, default=2.0, help="placements (and limits): request rate")
    p.add_argument("--robots", default="32,48,64", help="placements: total robot counts")
    p.add_argument("--loads", default="", help="placements: total demand as shares of the GPUs' capacity, "
                   "e.g. 0.8,0.9,1.0 (instead of --robots)")
    p.add_argument("--deadline", type=float, default=0.0, help="deadline in ms (default: the paper's for --arch)")
    p.add_argument("--target", type=float, default=0.98)
    p.add_argument("--max-robots", type=int, default=256, help="limit search: most robots per GPU")
    p.add_argument("--epochs", type=int, default=3)
    p.add_argument("--duration", type=float, default=10.0)
    p.add_argument("--drain", type=float, default=1.0, help="seconds replies may still come after each epoch")
    p.add_argument("--limit-epochs", type=int, default=2)
    p.add_argument("--limit-duration", type=float, default=5.0)
    p.add_argument("--limit-start", type=int, default=8, help="limit search: first robot count")
    p.add_argument("--limits-cache", default="", help="JSON file of measured limits, read and extended")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="")
    args = p.parse_args(argv)
    if args.experiment == "limits" and not args.limits_cache:
        p.error("limits: --limits-cache is needed (the file the measured limits go to)")
    if args.deadline:
        PAPER_DEADLINES_MS.setdefault(args.arch, args.deadline)
    # Checked before any model is built or limit measured (a traceback, or a run that quietly measured something else).
    if args.arch not in PAPER_DEADLINES_MS:
        p.error(f"--arch {args.arch!r} has no paper deadline: give --deadline")
    if args.experiment == "placements" and args.arch2 not in PAPER_DEADLINES_MS:
        p.error(f"--arch2: expected one of {', '.join(PAPER_DEADLINES_MS)}, got {args.arch2!r}")
    if args.gpus < 1:
        p.error(f"--gpus: expected at least 1, got {args.gpus}")
    if args.experiment == "strategies" and len(args.shares.split(",")) != len(args.rates.split(",")):
        # zip() dropped the variants past the shorter list: they got no robots, and the stated load was wrong.
        p.error(f"--shares: expected one share per --rates entry ({len(args.rates.split(','))}), got {args.shares!r}")
    try:
        engine_config({"kind": args.engine, "max_batch": args.max_batch})
    except ConfigError as exc:
        p.error(f"--max-batch or --engine: {exc}")
    if args.out and (why := unwritable(args.out)):
        p.error(f"--out: {why}")
    devices = args.devices.split(",")
    engine = {"kind": args.engine, "max_batch": args.max_batch}
    if args.sm_table:
        engine["sm_table"] = args.sm_table
    sim = {"epochs": args.epochs, "duration_s": args.duration, "drain_s": args.drain, "seed": args.seed}
    limit_sim = {"epochs": args.limit_epochs, "duration_s": args.limit_duration, "drain_s": args.drain,
                 "seed": args.seed}
    import torch

    gpu = torch.cuda.get_device_name(torch.device(devices[0])) if devices[0].startswith("cuda") else "cpu"
    t0 = time.monotonic()
    run = {"strategies": exp_strategies, "placements": exp_placements, "limits": exp_limits}[args.experiment]
    pool = DevicePool(devices)
    try:
        result = run(args, engine, sim, limit_sim, pool, gpu)
    finally:
        pool.close()
    from capacity import source_commit

    commit = source_commit(short=True) or ""
    result["meta"] = {"experiment": args.experiment, "date": datetime.date.today().isoformat(), "commit": commit,
                      "device": gpu,
                      "devices": devices, "torch": torch.__version__, "wall_s": round(time.monotonic() - t0, 1),
                      "command": "python bench/traffic.py " + " ".join(sys.argv[1:] if argv is None else argv)}
    if args.out:
        from services.executor.simulation import _json_safe

        with open(args.out, "w") as fh:  # NaN and Infinity are not JSON (misses_vs_ip when IP missed nothing): null
            json.dump(_json_safe(result), fh, indent=2, default=str, allow_nan=False)
    for v in result["variants"]:
        print(f"limit {v['name']:<12} {v['hz']:g} Hz: {v['limit']} robots per GPU" + (f", {v['robots']} robots"
                                                                                    if v["robots"] else ""))
    print(f"{'run':<12}{'robots':>7}{'sent':>8}{'misses':>8}{'SLO-AT':>9}{'vs IP':>8}  assignment")
    for r in result["rows"]:
        robots = r.get("robots", sum(v["robots"] for v in result["variants"]))
        print(f"{r['label']:<12}{robots:>7}{r['sent']:>8}{r['misses']:>8}{100 * r['slo_attainment']:>8.1f}%"
              f"{r.get('misses_vs_ip', float('nan')):>8.2f}  {r['assignment']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
