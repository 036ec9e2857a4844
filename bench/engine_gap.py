"""CPU gap between locksteps under saturating load, read from the engine's telemetry.

Keeps every model's queue non-empty for a while (so locksteps run back to back), then
reports the host-side gap (observing one lockstep's end -> next lockstep issued) and the
device-side gap (last kernel of one lockstep -> first kernel of the next, CUDA events),
median and p99, plus lockstep durations and stage overlap.

    python bench/engine_gap.py --models heavytoy:full --import bench.models --seconds 10 --out gap.json
    python bench/engine_gap.py --models pi0:full --sm-table bench/results/sm_table_h100_zoo.json --ahead off,on

``--ahead`` runs several engines one after the other over the same models (launch-ahead off,
on, or with a given slack in us); ``--rate`` replaces the saturating load by open-loop arrivals.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import json
import logging
import os
import sys
import threading
import time
from collections import defaultdict

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from services.executor.engine import ServedModel  # noqa: E402
from services.executor.lockstep import LockstepEngine  # noqa: E402
from services.executor.scheduler import Request  # noqa: E402
from services.executor.telemetry import summarize  # noqa: E402
from shared.config import ConfigError, EngineConfig, engine_config  # noqa: E402
from shared.files import unwritable  # noqa: E402
from shared.models import build_model  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from capacity import meta  # noqa: E402


def payloads(model, n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    io = model.io
    return [(rng.integers(0, 256, (len(io.cameras), *io.image_shape), dtype=np.uint8),
             rng.standard_normal(io.state_dim).astype(np.float32),
             rng.integers(1, 200, io.prompt_len).astype(np.int64)) for _ in range(n)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="heavytoy:full", help="comma-separated arch:size; repeats are co-located variants")
    ap.add_argument("--import", dest="imports", action="append", default=["bench.models"],
                    help="module registering extra architectures (bench.models is always imported)")
    ap.add_argument("--seconds", type=float, default=10.0, help="measured seconds per run, after 1 s of warm-up")
    ap.add_argument("--max-batch", type=int, default=2)
    ap.add_argument("--sm-policy", default="table", choices=["table", "none", "static"])
    ap.add_argument("--static-sms", type=int, default=0)
    ap.add_argument("--sm-table", default=None)
    ap.add_argument("--profile-dir", default="state/profiles")
    ap.add_argument("--depth", type=int, default=8, help="pending requests kept per model")
    ap.add_argument("--out", default=None)
    ap.add_argument("--telemetry", default=None, help="also write per-lockstep JSONL here")
    ap.add_argument("--ahead", default="on",
                    help="comma-separated engine runs over the same models: off (no launch-ahead), on (default "
                         "slack), or a slack in us (e.g. off,100,200,400)")
    ap.add_argument("--rate", type=float, default=0.0,
                    help="open-loop Poisson arrivals, requests/s per model (0: keep --depth requests queued)")
    args = ap.parse_args()
    # Checked before any model is built: a bad value used to fail after the warm-up, or run on to no locksteps.
    if not args.seconds > 0:
        ap.error(f"--seconds: expected a positive number, got {args.seconds}")
    if not args.rate >= 0:
        ap.error(f"--rate: expected 0 or a positive rate, got {args.rate}")
    if args.depth < 1:
        ap.error(f"--depth: expected at least 1, got {args.depth}")
    try:
        engine_config({"kind": "robion", "max_batch": args.max_batch, "sm_policy": args.sm_policy,
                       "static_sms": args.static_sms})
    except ConfigError as exc:
        ap.error(f"--max-batch, --sm-policy or --static-sms: {exc}")
    for variant in (v.strip() for v in args.ahead.split(",")):
        try:
            if variant not in ("on", "off"):
                float(variant)
        except ValueError:
            ap.error(f"--ahead: expected off, on or a slack in us, got {variant!r}")
    if args.out and (why := unwritable(args.out)):
        ap.error(f"--out: {why}")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    for mod in args.imports:
        importlib.import_module(mod)

    device = torch.device("cuda:0" if torch.cuda.is_available() else "cpu")
    models = {}
    for i, spec in enumerate(args.models.split(",")):
        arch, _, size = spec.partition(":")
        models[f"m{i}-{arch}"] = build_model(arch, size or "full", seed=i, device=device)
    runs = []
    for variant in args.ahead.split(","):
        runs.append(measure(args, models, device, variant.strip()))
        gc.collect()
        if device.type == "cuda":
            torch.cuda.empty_cache()
    out = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
           "torch": torch.__version__, "models": args.models, "max_batch": args.max_batch,
           "sm_policy": args.sm_policy, "rate": args.rate, "runs": runs, "meta": meta(str(device))}
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)
    fmt = lambda v: "-" if v is None else f"{v:.0f}"  # noqa: E731
    load = f"Poisson {args.rate:g} req/s per model" if args.rate else f"saturating (depth {args.depth})"
    print(f"\n{args.models} | policy {args.sm_policy} | {load} | {out['device']}")
    print(f"{'launch-ahead':<13}{'steps':>6}{'req/s':>7}{'host gap med/p99':>18}{'GPU idle med/p99':>18}"
          f"{'later stage':>12}{'launch':>8}{'ahead':>11}{'admit early med/p99':>21}{'overlap':>9}")
    for r in runs:
        s = r["summary"]
        cg, gg, gl, lu, ae = s["cpu_gap_us"], s["gpu_gap_us"], s["gpu_gap_last_us"], s["launch_us"], s["admit_early_us"]
        print(f"{r['ahead']:<13}{s['locksteps']:>6}{r['requests_per_s']:>7.0f}"
              f"{fmt(cg['median']) + ' / ' + fmt(cg['p99']):>18}{fmt(gg['median']) + ' / ' + fmt(gg['p99']):>18}"
              f"{fmt(gl['median']):>12}{fmt(lu['median']):>8}{str(s['ahead']) + '/' + str(s['back_to_back']):>11}"
              f"{fmt(ae['median']) + ' / ' + fmt(ae['p99']):>21}{str(s['overlapping']) + '/' + str(s['co_running']):>9}")


def measure(args, models: dict, device: torch.device, variant: str) -> dict:
    """One engine over ``models`` with launch-ahead ``variant`` (off, on, or a slack in us), under load."""
    ahead = variant != "off"
    slack = float(variant) if variant not in ("on", "off") else None
    cfg = EngineConfig(kind="robion", max_batch=args.max_batch, sm_policy=args.sm_policy, static_sms=args.static_sms,
                       sm_table=args.sm_table, profile_dir=args.profile_dir, telemetry_file=args.telemetry,
                       max_queue=100000)
    served = {name: ServedModel(name, m, 1.0) for name, m in models.items()}
    answered = [0]

    def sink(results):
        answered[0] += len(results)

    engine = LockstepEngine(served, cfg, device, sink, launch_ahead=ahead, launch_ahead_slack_us=slack)
    t0 = time.perf_counter()
    engine.prepare()
    prepare_s = time.perf_counter() - t0
    pools = {name: payloads(m, 16, i) for i, (name, m) in enumerate(models.items())}
    rng = np.random.default_rng(0)
    next_arrival = {name: time.monotonic() for name in models}

    stop = threading.Event()
    # A daemon, and stopped whatever happens below: a failure in the load loop left the engine's thread running, and
    # the process waiting on it for good.
    loop = threading.Thread(target=engine.run, args=(stop,), daemon=True)
    loop.start()
    sent = 0
    warm_end = time.monotonic() + 1.0
    end = warm_end + args.seconds
    answered0, t_meas = answered[0], warm_end
    cleared = False
    try:
        while time.monotonic() < end:
            if not cleared and time.monotonic() >= warm_end:
                engine.telemetry.clear()
                answered0, cleared, t_meas = answered[0], True, time.monotonic()
            now = time.monotonic()
            if args.rate:
                due = {}
                for name in models:
                    while next_arrival[name] <= now:
                        due[name] = due.get(name, 0) + 1
                        next_arrival[name] += rng.exponential(1.0 / args.rate)
            else:
                due = {name: args.depth - depth for name, depth in engine.queues.depths().items()}
            for name, n in due.items():
                for _ in range(n):
                    img, state, tok = pools[name][sent % 16]
                    now = time.monotonic()
                    engine.submit(Request(id=str(sent), robot="bench", model=name, images=img, state=state,
                                          tokens=tok, arrival=now, deadline=now + 60))
                    sent += 1
            time.sleep(0.0002)
        records = engine.telemetry.records()
        served_n = answered[0] - answered0
        elapsed = time.monotonic() - t_meas
    finally:
        stop.set()
        loop.join(60)

    summary = summarize(records)
    by_pair: dict[str, list[float]] = defaultdict(list)
    for r in records:
        by_pair[f"{r.vlm_arch}:{r.vlm_batch}|{r.action_arch}:{r.action_batch}|{r.sm_level}"].append(r.duration_ms)
    run = {
        "ahead": variant if variant != "on" else f"on ({engine.launch_ahead_slack_us:g})",
        "launch_ahead": engine._launch_ahead, "slack_us": engine.launch_ahead_slack_us, "missed": engine.ahead_missed,
        "seconds": elapsed, "requests_per_s": served_n / elapsed, "prepare_s": prepare_s,
        "prepare_breakdown_s": engine.prepare_s, "summary": summary,
        "durations_ms": {k: {"n": len(v), "mean": float(np.mean(v)), "std": float(np.std(v))}
                         for k, v in sorted(by_pair.items())},
    }
    del engine
    return run

if __name__ == "__main__":
    main()
