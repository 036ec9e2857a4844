"""CPU gap between locksteps under saturating load, read from the engine's telemetry.

Keeps every model's queue non-empty for a while (so locksteps run back to back), then
reports the host-side gap (observing one lockstep's end -> next lockstep issued) and the
device-side gap (last kernel of one lockstep -> first kernel of the next, CUDA events),
median and p99, plus lockstep durations and stage overlap.

    python bench/engine_gap.py --models heavytoy:full --import bench.models --seconds 10 --out gap.json
"""

from __future__ import annotations

import argparse
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
from shared.config import EngineConfig  # noqa: E402
from shared.models import build_model  # noqa: E402


def payloads(model, n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    io = model.io
    return [(rng.integers(0, 256, (len(io.cameras), *io.image_shape), dtype=np.uint8),
             rng.standard_normal(io.state_dim).astype(np.float32),
             rng.integers(1, 200, io.prompt_len).astype(np.int64)) for _ in range(n)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="heavytoy:full", help="comma-separated arch:size; repeats are co-located variants")
    ap.add_argument("--import", dest="imports", action="append", default=["bench.models"])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--max-batch", type=int, default=2)
    ap.add_argument("--sm-policy", default="table", choices=["table", "none", "static"])
    ap.add_argument("--static-sms", type=int, default=0)
    ap.add_argument("--sm-table", default=None)
    ap.add_argument("--profile-dir", default="state/profiles")
    ap.add_argument("--depth", type=int, default=8, help="pending requests kept per model")
    ap.add_argument("--out", default=None)
    ap.add_argument("--telemetry", default=None, help="also write per-lockstep JSONL here")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    for mod in args.imports:
        importlib.import_module(mod)

    device = torch.device("cuda:0" if torch.cuda.is_available() else "cpu")
    models = {}
    for i, spec in enumerate(args.models.split(",")):
        arch, _, size = spec.partition(":")
        models[f"m{i}-{arch}"] = build_model(arch, size or "full", seed=i, device=device)
    cfg = EngineConfig(kind="robion", max_batch=args.max_batch, sm_policy=args.sm_policy, static_sms=args.static_sms,
                       sm_table=args.sm_table, profile_dir=args.profile_dir, telemetry_file=args.telemetry)
    served = {name: ServedModel(name, m, 1.0) for name, m in models.items()}
    answered = [0]

    def sink(results):
        answered[0] += len(results)

    engine = LockstepEngine(served, cfg, device, sink)
    t0 = time.perf_counter()
    engine.prepare()
    prepare_s = time.perf_counter() - t0
    pools = {name: payloads(m, 16, i) for i, (name, m) in enumerate(models.items())}

    stop = threading.Event()
    loop = threading.Thread(target=engine.run, args=(stop,))
    loop.start()
    sent = 0
    warm_end = time.monotonic() + 1.0
    end = warm_end + args.seconds
    cleared = False
    while time.monotonic() < end:
        if not cleared and time.monotonic() >= warm_end:
            engine.telemetry.clear()
            answered0, cleared, t_meas = answered[0], True, time.monotonic()
        depths = engine.queues.depths()
        for name, depth in depths.items():
            for _ in range(args.depth - depth):
                img, state, tok = pools[name][sent % 16]
                now = time.monotonic()
                engine.submit(Request(id=str(sent), robot="bench", model=name, images=img, state=state, tokens=tok,
                                      arrival=now, deadline=now + 60))
                sent += 1
        time.sleep(0.0002)
    records = engine.telemetry.records()
    served_n = answered[0] - answered0
    elapsed = time.monotonic() - t_meas
    stop.set()
    loop.join(60)

    summary = summarize(records)
    by_pair: dict[str, list[float]] = defaultdict(list)
    for r in records:
        by_pair[f"{r.vlm_batch}|{r.action_batch}|{r.sm_level}"].append(r.duration_ms)
    out = {
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "torch": torch.__version__, "models": args.models, "max_batch": args.max_batch, "sm_policy": args.sm_policy,
        "seconds": elapsed, "requests_per_s": served_n / elapsed, "prepare_s": prepare_s,
        "prepare_breakdown_s": engine.prepare_s, "summary": summary,
        "durations_ms": {k: {"n": len(v), "mean": float(np.mean(v))} for k, v in sorted(by_pair.items())},
        "table_profile_s": engine.table.profile_s if engine.table else None,
    }
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)
    cg, gg = summary["cpu_gap_us"], summary["gpu_gap_us"]
    fmt = lambda v: "-" if v is None else f"{v:.1f}"  # noqa: E731
    print(f"\n{args.models} | policy {args.sm_policy} | {summary['locksteps']} locksteps in {elapsed:.1f} s | "
          f"{out['requests_per_s']:.1f} req/s")
    print(f"{'metric':<28}{'median':>10}{'p99':>10}{'n':>8}")
    print(f"{'CPU gap (us)':<28}{fmt(cg['median']):>10}{fmt(cg['p99']):>10}{cg['n']:>8}")
    print(f"{'GPU idle gap (us)':<28}{fmt(gg['median']):>10}{fmt(gg['p99']):>10}{gg['n']:>8}")
    print(f"overlapping locksteps: {summary['overlapping']}/{summary['co_running']}, "
          f"mean overlap {fmt(summary['mean_overlap_ms'])} ms, mean lockstep {fmt(summary['mean_duration_ms'])} ms")
    for k, v in out["durations_ms"].items():
        print(f"  vlm|action|SMs {k:<16} n={v['n']:<6} mean {v['mean']:.2f} ms")


if __name__ == "__main__":
    main()
