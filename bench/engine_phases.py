"""Where the host time between locksteps goes: each phase of a lockstep launch, timed.

Fills the queue up front (no feeder thread competing for the GIL), steps the engine inline
and wraps the runner, the queues and the stages with timers. A diagnostic for the CPU gap.

    python bench/engine_phases.py --models heavytoy:full --locksteps 300
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
import time
from collections import defaultdict

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bench.engine_gap import payloads  # noqa: E402
from services.executor.engine import ServedModel  # noqa: E402
from services.executor.lockstep import LockstepEngine  # noqa: E402
from services.executor.scheduler import Request  # noqa: E402
from shared.config import EngineConfig  # noqa: E402
from shared.models import build_model  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default="heavytoy:full", help="comma-separated arch:size (runs on cuda:0)")
    ap.add_argument("--import", dest="imports", action="append", default=["bench.models"],
                    help="module registering extra architectures (bench.models is always imported)")
    ap.add_argument("--locksteps", type=int, default=300)
    ap.add_argument("--sm-policy", default="none", help="none or table (static needs static_sms, not set here)")
    ap.add_argument("--sm-table", default=None, help="SM table file (sm-policy table)")
    ap.add_argument("--fixed-noise", action="store_true", help="requests bring zero noise (none drawn at submit)")
    ap.add_argument("--ahead", action="store_true", help="launch-ahead on (off by default: time each launch phase in the gap)")
    ap.add_argument("--out", default=None, help="JSON of the per-phase medians and p99s")
    args = ap.parse_args()
    for mod in args.imports:
        importlib.import_module(mod)
    device = torch.device("cuda:0")
    models = {}
    for i, spec in enumerate(args.models.split(",")):
        arch, _, size = spec.partition(":")
        models[f"m{i}-{arch}"] = build_model(arch, size or "full", seed=i, device=device)
    cfg = EngineConfig(kind="robion", max_batch=2, sm_policy=args.sm_policy, sm_table=args.sm_table,
                       max_queue=100000)
    engine = LockstepEngine({n: ServedModel(n, m, 1.0) for n, m in models.items()}, cfg, device, lambda rs: None,
                            launch_ahead=args.ahead)
    engine.prepare()
    n_req = 2 * args.locksteps + 8
    for i in range(n_req):
        name = list(models)[i % len(models)]
        img, state, tok = payloads(models[name], 1, i)[0]
        now = time.monotonic()
        noise = np.zeros((models[name].io.horizon, models[name].io.action_dim), np.float32) if args.fixed_noise else None
        engine.submit(Request(str(i), "b", name, img, state, tok, now, now + 3600, noise=noise))

    spent: dict[str, list[float]] = defaultdict(list)

    def timed(obj, attr: str, label: str) -> None:
        fn = getattr(obj, attr)

        def wrapper(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                spent[label].append((time.perf_counter() - t0) * 1e6)
        setattr(obj, attr, wrapper)

    for attr in ("begin", "launch_handoff", "launch_action", "launch_vlm", "end_launch", "wait", "done"):
        timed(engine.runner, attr, f"runner.{attr}")
    timed(engine.queues, "take", "queues.take")
    for st in engine.stages.values():
        timed(st, "stage", "stages.stage")
        timed(st, "upload", "stages.upload")
        timed(st, "handoff", "stages.handoff")
    timed(engine, "_book", "engine._book")
    for _ in range(args.locksteps):
        engine.step()
    engine.finish()
    recs = engine.telemetry.records()[5:]
    rows = {k: {"median_us": float(np.median(v[5:])), "p99_us": float(np.percentile(v[5:], 99)), "n": len(v)}
            for k, v in spent.items()}
    cpu = [r.cpu_gap_us for r in recs if r.cpu_gap_us is not None]
    gpu = [r.gpu_gap_us for r in recs if r.gpu_gap_us is not None]
    rows["cpu_gap"] = {"median_us": float(np.median(cpu)), "p99_us": float(np.percentile(cpu, 99)), "n": len(cpu)}
    rows["gpu_gap"] = {"median_us": float(np.median(gpu)), "p99_us": float(np.percentile(gpu, 99)), "n": len(gpu)}
    launch = [r.launch_us for r in recs if r.launch_us is not None]
    rows["launch (decide+issue)"] = {"median_us": float(np.median(launch)), "p99_us": float(np.percentile(launch, 99)),
                                     "n": len(launch)}
    # Host cost of single launches, each on an idle GPU.
    st = next(iter(engine.stages.values()))
    runner = engine.runner
    probes = {
        "replay action graph b2": (runner.action_stream, lambda: st.action_graphs[2].replay()),
        "replay VLM graph b2 (unrestricted)": (runner.vlm_stream, lambda: st.vlm_graphs[(2, None)].replay()),
        "replay VLM graph b2 (green) on VLM stream": (None, None),
        "handoff copy b2": (runner.action_stream, lambda: st.handoff(2)),
        "handoff copy b2 after VLM replay": (runner.action_stream, lambda: st.handoff(2)),
        "replay VLM graph b2 on its green stream": (None, None),
        "D2H result b2": (runner.action_stream, lambda: st.host_out[2][0].copy_(st.dev_out[2], non_blocking=True)),
        "event record": (runner.action_stream, lambda: torch.cuda.Event().record(runner.action_stream)),
    }
    green_level = next((lv for (b, lv) in st.vlm_graphs if b == 2 and lv is not None), None)
    vkey = (2, green_level)
    if green_level is not None:
        probes["replay VLM graph b2 (green) on VLM stream"] = (runner.vlm_stream,
                                                               lambda: st.vlm_graphs[(2, green_level)].replay())
        probes["replay VLM graph b2 on its green stream"] = (engine.green.stream(green_level),
                                                             lambda: st.vlm_graphs[(2, green_level)].replay())
    else:
        del probes["replay VLM graph b2 on its green stream"], probes["replay VLM graph b2 (green) on VLM stream"]
    for label, (stream, fn) in probes.items():
        costs = []
        for _ in range(60):
            if "after VLM replay" in label:  # a green-context graph launched just before
                torch.cuda.set_stream(runner.vlm_stream)
                st.vlm_graphs[vkey].replay()
            torch.cuda.set_stream(stream)
            t0 = time.perf_counter()
            fn()
            costs.append((time.perf_counter() - t0) * 1e6)
            torch.cuda.set_stream(torch.cuda.default_stream())
            stream.synchronize()
            runner.vlm_stream.synchronize()
        rows[label] = {"median_us": float(np.median(costs[10:])), "p99_us": float(np.percentile(costs[10:], 99)), "n": 50}
    rows["prestage hits/misses"] = {"median_us": float(sum(s.prestage_hits for s in engine.stages.values())),
                                    "p99_us": float(sum(s.prestage_misses for s in engine.stages.values())), "n": 0}
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rows, f, indent=1)
    print(f"{'phase':<44}{'median us':>12}{'p99 us':>12}")
    for k, v in rows.items():
        print(f"{k:<44}{v['median_us']:>12.1f}{v['p99_us']:>12.1f}")


if __name__ == "__main__":
    main()
