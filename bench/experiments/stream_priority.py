"""Experiment: the lockstep with the action stream at a higher CUDA priority than the VLM stream.

In a guarded lockstep the VLM stage runs on a green context of L SMs and the action stage on a
plain stream that may use every SM. The action stage is the lockstep's tail for pi0 and GR00T
(``action_interference.py``): its ~1400 short dependent kernels each wait for SM slots, and on
the VLM's SMs they queue behind the VLM's GEMM blocks. A graph launched into a stream runs its
kernels at that stream's priority, so the block scheduler can hand a freed slot to a pending
action block first. Variants per (model, L), the same captured graphs, only the streams differ:
  base      both streams at the default priority (main)
  act_hi    action stream at the highest priority, VLM stream at the default
  vlm_hi    the reverse (a control)

    OUT=/tmp python bench/experiments/stream_priority.py
    MODELS="pi0:80,96" ROUNDS=2 OUT=/tmp python bench/experiments/stream_priority.py
"""

from __future__ import annotations

import datetime
import gc
import json
import os
import statistics
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from bench.experiments.timing import pct  # noqa: E402
from services.executor.graphs import GraphPools, GraphStages  # noqa: E402
from services.executor.lockstep import CudaRunner  # noqa: E402
from services.executor.profiler import lockstep_samples  # noqa: E402
from services.executor.sm import GreenStreams  # noqa: E402
from shared.models import build_model  # noqa: E402

B = 2
DEFAULT_MODELS = "pi0:80,96;groot_n15:96,112;smolvla:56,64;xr0:104"


def run_model(arch: str, levels: list[int], device: torch.device, rounds: int, repeats: int) -> dict:
    model = build_model(arch, "full", device=device)
    green = GreenStreams(device, levels)
    runner = CudaRunner(device)
    st = GraphStages(model, device, [B], 0, GraphPools.create(), green, runner.vlm_stream, runner.action_stream)
    st.allocate()
    st.capture_action()  # as the engine captures them (no SM table: whole-GPU action plan)
    st.capture_vlm(B, set(levels))
    _, hi = torch.cuda.Stream.priority_range()  # (lowest, highest); lower numbers run first
    streams = {"base": (0, 0), "act_hi": (0, hi), "vlm_hi": (hi, 0)}
    runners = {}
    for name, (vp, ap) in streams.items():
        r = CudaRunner(device)
        r.vlm_stream, r.action_stream = torch.cuda.Stream(device, priority=vp), torch.cuda.Stream(device, priority=ap)
        runners[name] = r
    samples: dict[str, list] = {}
    for _ in range(rounds):
        for lv in levels:
            for name, r in runners.items():
                samples.setdefault(f"{name}_{lv}", []).extend(
                    (t.vlm_ms, t.action_ms, t.duration_ms) for t in lockstep_samples(r, st, B, st, B, lv, repeats, 3))
    med = {k: {"vlm": round(statistics.median(x[0] for x in v), 3), "action": round(statistics.median(x[1] for x in v), 3),
               "lockstep": round(statistics.median(x[2] for x in v), 3), "lockstep_p99": round(pct([x[2] for x in v], 0.99), 3)}
           for k, v in samples.items()}
    return {"arch": arch, "levels": levels, "priorities": {k: list(v) for k, v in streams.items()},
            "median_ms": med, "samples": samples}


def main() -> None:
    device = torch.device("cuda", 0)
    torch.cuda.set_device(device)
    out_dir = os.environ.get("OUT", ".")
    rounds, repeats = int(os.environ.get("ROUNDS", "3")), int(os.environ.get("REPEATS", "20"))
    out = {"experiment": "stream_priority", "gpu": torch.cuda.get_device_name(device), "torch": torch.__version__,
           "date": datetime.date.today().isoformat(), "commit": os.environ.get("ROBION_COMMIT", "unknown"),
           "batch": B, "rounds": rounds, "repeats": repeats, "models": []}
    for item in os.environ.get("MODELS", DEFAULT_MODELS).split(";"):
        arch, _, lv = item.partition(":")
        out["models"].append(run_model(arch, [int(x) for x in lv.split(",")], device, rounds, repeats))
        gc.collect()
        torch.cuda.empty_cache()
        print(f"{arch}: done", flush=True)
    with open(os.path.join(out_dir, os.environ.get("OUT_NAME", "kernel_exp_stream_priority_h100.json")), "w") as f:
        json.dump(out, f, indent=1)
    print(f"\nVLM b={B} on L SMs + action b={B}, lockstep ms p50 (p99); VLM / action span inside")
    print(f"{'model':>10} {'L':>4} {'variant':>8} {'lockstep':>16} {'VLM in':>7} {'act in':>7}")
    for res in out["models"]:
        for lv in res["levels"]:
            for name in res["priorities"]:
                m = res["median_ms"][f"{name}_{lv}"]
                print(f"{res['arch']:>10} {lv:>4} {name:>8} {m['lockstep']:>8.2f} ({m['lockstep_p99']:>5.2f}) "
                      f"{m['vlm']:>7.2f} {m['action']:>7.2f}")


if __name__ == "__main__":
    main()
