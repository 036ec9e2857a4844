"""Intra-GPU vs inter-GPU stage disaggregation (paper experiment 8): robot capacity of N GPUs.

- **intra**: Robion (``--intra-engine``, default ``robion``) replicated on every GPU. Robots are
  pinned to GPUs and each GPU's executor serves its own robots with nothing shared, so the
  capacity of N GPUs is N x the capacity measured on the first device (measuring the N engines
  at once in this one process would add GIL contention that separate executor processes do
  not have).
- **dis-a:b**: one ``interdisagg`` engine over all N devices, the first a running only the VLM
  stage and the other b only the action stage; its capacity is searched as a whole.

Each row is a capacity search (services/executor/simulation.py: growth then bisection,
screened points, early stop) or a sweep over ``--sweep`` counts; the JSON is rewritten after
every row, so an interrupted run keeps the rows it finished.

    python bench/interdisagg.py --arch pi0 --size full --devices 0,1,2,3 --start 16 \\
        --out bench/results/interdisagg_pi0_4gpu.json
    # CPU smoke (tiny models; "cpu" repeated = that many stage workers on the CPU)
    python bench/interdisagg.py --arch pi0 --size tiny --devices cpu,cpu --sweep 1,2 --epochs 1 --duration 1
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from capacity import _point_dict, bad_arguments, meta, unknown_models  # noqa: E402

from services.executor.simulation import (PAPER_DEADLINES_MS, EngineHost, SimConfig, _json_safe,  # noqa: E402
                                          compare_capacity, engine_factory, served_models)
from shared.config import ConfigError, engine_config, parse_devices  # noqa: E402
from shared.files import write_atomic  # noqa: E402

SCHEMA = "robion.interdisagg/1"
log = logging.getLogger("bench.interdisagg")


def default_devices() -> str:
    """Every visible GPU; raises ValueError where there is none."""
    import torch

    if not torch.cuda.is_available():
        raise ValueError("no CUDA device here; give e.g. --devices cpu,cpu for a CPU run")
    return ",".join(str(i) for i in range(torch.cuda.device_count()))


def parse_splits(text: str | None, n: int) -> list[tuple[int, int]]:
    """``"1:3,3:1"`` -> [(1, 3), (3, 1)]; default every a:b with a + b = n."""
    if not text:
        return [(a, n - a) for a in range(1, n)]
    out = []
    for item in filter(None, (s.strip() for s in text.split(","))):
        a, sep, b = item.partition(":")
        if not sep or not a.isdigit() or not b.isdigit() or int(a) < 1 or int(b) < 1 or int(a) + int(b) != n:
            raise ValueError(f"{item!r} is not a:b with a, b >= 1 and a + b = {n} (the devices given)")
        out.append((int(a), int(b)))
    return out


def search(label: str, host: EngineHost, model: str, args, sim: SimConfig, robots: list[int] | None) -> dict:
    """``robots``: the counts of --sweep, or None to search."""
    try:
        res = compare_capacity({label: host}, model, args.hz, sim, args.target, robots, args.start, args.max_robots,
                               early_stop=True, progress=not args.quiet,
                               screen_epochs=args.screen_epochs or None)[label]
    finally:
        host.close()
    return {"capacity": res.capacity, "prepare_s": res.prepare_s,
            "curve": [_point_dict(p) for p in sorted(res.points, key=lambda p: p.robots)]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--arch", default="pi0")
    p.add_argument("--size", default="full", help="model size: full or tiny")
    p.add_argument("--devices", help="the N devices: cuda:N or indices, comma-separated; 'cpu' (repeatable) "
                                     "for a CPU run (default: every visible GPU)")
    p.add_argument("--splits", help="a:b VLM:action device splits, comma-separated (default: every split)")
    p.add_argument("--intra-engine", default="robion", help="engine kind replicated per GPU")
    p.add_argument("--no-intra", action="store_true", help="measure only the disaggregated splits")
    p.add_argument("--sm-table", help="SM table for the intra engine (robion)")
    p.add_argument("--handoff-slots", type=int, default=4, help="interdisagg receive slots per model and batch size")
    p.add_argument("--max-batch", type=int, default=2)
    p.add_argument("--hz", type=float, default=2.0)
    p.add_argument("--epochs", type=int, default=5)
    p.add_argument("--duration", type=float, default=10.0, help="seconds of sending per epoch")
    p.add_argument("--drain", type=float, default=1.0)
    p.add_argument("--target", type=float, default=0.98)
    p.add_argument("--network", default="wifi7")
    p.add_argument("--deadline", type=float, help="deadline in ms (default: the paper's for --arch)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--start", type=int, default=1, help="first robot count of each search")
    p.add_argument("--max-robots", type=int, default=512)
    p.add_argument("--screen-epochs", type=int, default=1, help="epochs of the bracketing points (0: all)")
    p.add_argument("--sweep", help="comma-separated robot counts to measure instead of searching")
    p.add_argument("--out", type=Path, help="JSON results file")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--log-level", default="WARNING")
    args = p.parse_args(argv)
    # The measurement's own arguments, checked as bench/capacity.py checks them, before any model is built (a bad
    # one was a traceback, or a capacity of 0 in every row with exit 0).
    try:
        robots = [int(x) for x in args.sweep.split(",") if x.strip()] if args.sweep else None
    except ValueError:
        p.error(f"--sweep: expected comma-separated robot counts, got {args.sweep!r}")
    why = bad_arguments(args, robots) or unknown_models({args.arch: args.arch}, args.size)
    if why:
        p.error(why)
    try:
        engine_config({"kind": "interdisagg", "max_batch": args.max_batch, "handoff_slots": args.handoff_slots,
                       "vlm_devices": "cpu", "action_devices": "cpu"})
        if not args.no_intra:
            engine_config({"kind": args.intra_engine, "max_batch": args.max_batch})
    except ConfigError as exc:
        p.error(f"--max-batch, --handoff-slots or --intra-engine: {exc}")
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(name)s %(levelname)s %(message)s")

    try:
        devices = parse_devices(args.devices or default_devices(), required=True)
    except ValueError as exc:
        p.error(f"--devices: {exc}")
    n = len(devices)
    if n < 2:
        p.error("--devices: disaggregation needs at least 2 devices")
    try:
        splits = parse_splits(args.splits, n)
    except ValueError as exc:
        p.error(f"--splits: {exc}")
    deadline_ms = args.deadline or PAPER_DEADLINES_MS.get(args.arch)
    if deadline_ms is None:
        p.error(f"--deadline: the paper gives none for {args.arch!r}")
    sim = SimConfig(epochs=args.epochs, duration_s=args.duration, drain_s=args.drain, seed=args.seed,
                    network=args.network)
    doc: dict = {
        "schema": SCHEMA, "arch": args.arch, "target": args.target, "deadline_ms": deadline_ms, "devices": devices,
        "rows": [], "complete": False,
        "settings": {"size": args.size, "hz": args.hz, "epochs": args.epochs, "duration_s": args.duration,
                     "drain_s": args.drain, "network": args.network, "max_batch": args.max_batch, "seed": args.seed,
                     "mode": "sweep" if args.sweep else "search", "sweep": args.sweep, "start": args.start,
                     "max_robots": args.max_robots, "screen_epochs": args.screen_epochs or None,
                     "intra_engine": None if args.no_intra else args.intra_engine, "sm_table": args.sm_table,
                     "handoff_slots": args.handoff_slots, "splits": [f"{a}:{b}" for a, b in splits]},
        "meta": {**meta(devices[0]), "devices": devices},
    }

    def write() -> None:
        if args.out is None:
            return
        write_atomic(args.out, json.dumps(_json_safe(doc), indent=1) + "\n")

    t0 = time.monotonic()
    # One set of weights on the first device; the interdisagg engine copies it to its other devices.
    served = served_models({args.arch: args.arch}, args.size, devices[0], args.seed, {args.arch: deadline_ms})
    if not args.no_intra:
        overrides = {"max_batch": args.max_batch}
        if args.sm_table:
            overrides["sm_table"] = args.sm_table
        host = EngineHost(engine_factory(args.intra_engine, served, devices[0], **overrides), label="intra")
        row = search("intra", host, args.arch, args, sim, robots)
        per_gpu = row["capacity"]
        doc["rows"].append({**row, "label": "intra", "engine": args.intra_engine, "devices": devices,
                            "measured_on": devices[0], "capacity_per_gpu": per_gpu, "capacity": per_gpu * n})
        write()
    for a, b in splits:
        label = f"dis-{a}:{b}"
        vlm, act = devices[:a], devices[a:]
        host = EngineHost(engine_factory("interdisagg", served, devices[0], max_batch=args.max_batch,
                                         handoff_slots=args.handoff_slots, vlm_devices=",".join(vlm),
                                         action_devices=",".join(act)), label=label)
        row = search(label, host, args.arch, args, sim, robots)
        doc["rows"].append({**row, "label": label, "engine": "interdisagg", "vlm_devices": vlm,
                            "action_devices": act, "capacity_per_gpu": row["capacity"] / n})
        write()
    dis = [r for r in doc["rows"] if r["engine"] == "interdisagg"]
    best = max(dis, key=lambda r: r["capacity"])
    doc["best_dis"] = best["label"]
    intra = next((r for r in doc["rows"] if r["label"] == "intra"), None)
    if intra is not None:
        doc["intra_over_best_dis"] = intra["capacity"] / best["capacity"] if best["capacity"] else None
    doc["complete"] = True
    doc["meta"]["wall_s"] = round(time.monotonic() - t0, 1)
    write()

    print(f"{args.arch} on {n} devices ({', '.join(devices)}), {args.hz:g} Hz, deadline {deadline_ms:g} ms, "
          f"target {100 * args.target:g}%")
    print(f"{'run':<10}{'VLM':>18}{'action':>24}{'robots':>8}{'per GPU':>9}{'vs intra':>10}")
    for r in doc["rows"]:
        vlm = ",".join(r.get("vlm_devices", ["all"]))
        act = ",".join(r.get("action_devices", ["all"]))
        ratio = r["capacity"] / intra["capacity"] if intra is not None and intra["capacity"] else float("nan")
        print(f"{r['label']:<10}{vlm:>18}{act:>24}{r['capacity']:>8}{r['capacity_per_gpu']:>9.1f}{ratio:>10.2f}")
    if args.out:
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
