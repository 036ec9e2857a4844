"""Experiment: why the action stage slows down beside the VLM, and whether confining it helps.

In a guarded lockstep (VLM b=2 on a green context of L SMs, action stage b=2 on a plain
stream) the action stage of pi0 takes about 17.7 ms at every L from 72 to 96, against 11.0
ms alone on the whole GPU, while the VLM alone on L SMs takes 14.8-12.4 ms: the action stage
is the lockstep's tail, and its slowdown does not depend on how many SMs the VLM leaves free.
Three candidate causes, each with a variant here:

  stragglers   the unrestricted action stream puts some of its blocks on SMs the VLM holds,
               where they share the tensor and issue pipes with a GEMM; one slow block holds
               up a kernel, and the stage is ~1700 dependent kernels. Test: the same pair on a
               disjoint split (``cuDevSmResourceSplitByCount``) at the same L, the action stage
               alone on the remaining SMs and beside the VLM.
  shared GPU   HBM, L2 and the power budget (clocks) are shared whatever the SMs. Test: the
               action stage alone on its partition against beside the VLM on that partition
               (no SM is shared), and the SM clock sampled by nvidia-smi during each phase.
  wrong plan   the action graphs plan their GEMMs (and Triton grids) for 132 SMs. Test: the
               action graph captured through cuBLASLt planned for the SMs left (``plan``),
               and with the Triton grids resized as well (``plan+tri``).

Variants per (model, L), all with the VLM graph captured the way main does (cuBLASLt planned
for its SMs) and the engine's own graphs and runner:
  guarded         VLM on green L, action unrestricted (main's Robion lockstep)
  guarded_plan    the same, action graph planned for 132 - L SMs (cuBLASLt only)
  part            VLM on an L-SM partition, action on the rest, planned for it (the disjoint engine)
  part_tri        the same, Triton grids sized for the partition too
Reported per variant: VLM and action stage ms inside the lockstep, lockstep ms, and the stages
alone on their SMs; medians over interleaved rounds.

    OUT=/tmp python bench/experiments/action_interference.py
    MODELS=pi0:72,96 ROUNDS=2 OUT=/tmp python bench/experiments/action_interference.py
"""

from __future__ import annotations

import datetime
import gc
import json
import os
import statistics
import subprocess
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from bench.experiments.sm_target import sm_target  # noqa: E402
from bench.experiments.timing import replay_ms  # noqa: E402
from services.executor.graphs import GraphPools, GraphStages  # noqa: E402
from services.executor.lockstep import CudaRunner  # noqa: E402
from services.executor.profiler import lockstep_samples  # noqa: E402
from services.executor.sm import GreenStreams, sm_count, split_disjoint  # noqa: E402
from shared.models import build_model  # noqa: E402

B = 2
DEFAULT_MODELS = "pi0:72,96,112;groot_n15:80,96,112;xr0:96,104,112;smolvla:56,72"


class ClockLog:
    """nvidia-smi sampling SM clock and power every 50 ms into a file, read back per phase."""

    def __init__(self, path: str):
        self.path = path
        self.proc = None
        try:
            self.proc = subprocess.Popen(
                ["nvidia-smi", "--query-gpu=timestamp,clocks.sm,power.draw", "--format=csv,noheader,nounits",
                 "-lms", "50"], stdout=open(path, "w"), stderr=subprocess.DEVNULL)
        except OSError:
            pass
        self.phases: dict[str, list[tuple[float, float]]] = {}

    def mark(self, name: str, t0: float, t1: float) -> None:
        self.phases.setdefault(name, []).append((t0, t1))

    def summary(self) -> dict[str, dict[str, float]]:
        if self.proc is None:
            return {}
        self.proc.terminate()
        self.proc.wait()
        rows = []
        for line in open(self.path):
            parts = [p.strip() for p in line.split(",")]
            try:
                ts = datetime.datetime.strptime(parts[0], "%Y/%m/%d %H:%M:%S.%f").timestamp()
                rows.append((ts, float(parts[1]), float(parts[2])))
            except (ValueError, IndexError):
                continue
        out = {}
        for name, spans in self.phases.items():
            inside = [r for r in rows if any(a <= r[0] <= b for a, b in spans)]
            if inside:
                out[name] = {"sm_mhz": statistics.median(r[1] for r in inside),
                             "power_w": statistics.median(r[2] for r in inside), "samples": len(inside)}
        return out


def lockstep_times(runner: CudaRunner, st: GraphStages, repeats: int, warmup: int = 3) -> list[tuple]:
    """(VLM ms, action ms, lockstep ms) of ``repeats`` locksteps: action b=2 beside VLM b=2
    at level None (the graph under that key is the variant's)."""
    return [(t.vlm_ms, t.action_ms, t.duration_ms)
            for t in lockstep_samples(runner, st, B, st, B, None, repeats, warmup)]


def run_model(arch: str, levels: list[int], device: torch.device, rounds: int, repeats: int,
              clocks: ClockLog) -> dict:
    t0 = time.perf_counter()
    model = build_model(arch, "full", device=device)
    total = sm_count(device)
    green = GreenStreams(device, levels)
    runner = CudaRunner(device)
    st = GraphStages(model, device, [B], 0, GraphPools.create(), green, runner.vlm_stream, runner.action_stream)
    st.allocate()

    def cap_vlm(stream, sms):
        with sm_target(device, sms, lt=sms is not None):
            return st._capture(lambda: st._vlm_body(B), stream, st.pools.vlm)

    def cap_act(stream, sms, tri=False):
        with sm_target(device, sms, triton=tri, lt=sms is not None):
            return st._capture(lambda: st._action_body(B), stream, st.pools.action)

    vlm_full = cap_vlm(runner.vlm_stream, None)
    act_full = cap_act(runner.action_stream, None)
    parts, variants = {}, {}  # (variant, L) -> (vlm graph, action graph, runner)
    for lv in levels:
        vg = cap_vlm(green.stream(lv), lv)
        variants[("guarded", lv)] = (vg, act_full, runner)
        variants[("guarded_plan", lv)] = (vg, cap_act(runner.action_stream, total - lv), runner)
        part = parts[lv] = split_disjoint(device, lv)
        prun = CudaRunner(device)
        prun.vlm_stream, prun.action_stream = part.vlm_stream, part.action_stream
        pvg = cap_vlm(part.vlm_stream, part.vlm_sms)
        variants[("part", lv)] = (pvg, cap_act(part.action_stream, part.action_sms), prun)
        variants[("part_tri", lv)] = (pvg, cap_act(part.action_stream, part.action_sms, tri=True), prun)
    built_s = time.perf_counter() - t0

    samples: dict[str, list] = {}

    def timed(name, fn):
        a = time.time()
        res = fn()
        clocks.mark(f"{arch}:{name}", a, time.time())
        samples.setdefault(name, []).extend(res)

    for _ in range(rounds):
        timed("vlm_alone_full", lambda: replay_ms(vlm_full, runner.vlm_stream, repeats))
        timed("act_alone_full", lambda: replay_ms(act_full, runner.action_stream, repeats))
        for (name, lv), (vg, ag, run) in variants.items():
            st.vlm_graphs[(B, None)] = vg
            st.action_graphs[B] = ag
            if name in ("guarded", "part"):
                timed(f"vlm_alone_{name}_{lv}", lambda: replay_ms(vg, run.vlm_stream, repeats))
            if name != "guarded":
                timed(f"act_alone_{name}_{lv}", lambda: replay_ms(ag, run.action_stream, repeats))
            timed(f"lock_{name}_{lv}", lambda: lockstep_times(run, st, repeats))
    med = {}
    for k, v in samples.items():
        if k.startswith("lock_"):
            med[k] = {"vlm": round(statistics.median(x[0] for x in v), 3),
                      "action": round(statistics.median(x[1] for x in v), 3),
                      "lockstep": round(statistics.median(x[2] for x in v), 3)}
        else:
            med[k] = round(statistics.median(v), 3)
    res = {"arch": arch, "levels": levels, "rounds": rounds, "repeats": repeats, "built_s": round(built_s, 1),
           "partition_sms": {str(lv): [p.vlm_sms, p.action_sms] for lv, p in parts.items()},
           "median_ms": med, "samples": samples}
    return res


def main() -> None:
    device = torch.device("cuda", 0)
    torch.cuda.set_device(device)
    out_dir = os.environ.get("OUT", ".")
    spec = os.environ.get("MODELS", DEFAULT_MODELS)
    rounds = int(os.environ.get("ROUNDS", "3"))
    repeats = int(os.environ.get("REPEATS", "10"))
    clocks = ClockLog(os.path.join(out_dir, "action_interference_clocks.csv"))
    out = {"experiment": "action_interference", "gpu": torch.cuda.get_device_name(device), "torch": torch.__version__,
           "date": datetime.date.today().isoformat(), "commit": os.environ.get("ROBION_COMMIT", "unknown"),
           "batch": B, "models": []}
    for item in spec.split(";"):
        arch, _, lv = item.partition(":")
        res = run_model(arch, [int(x) for x in lv.split(",")], device, rounds, repeats, clocks)
        out["models"].append(res)
        gc.collect()
        torch.cuda.empty_cache()
        print(f"{arch}: built in {res['built_s']} s", flush=True)
    out["clocks"] = clocks.summary()
    path = os.path.join(out_dir, os.environ.get("OUT_NAME", "kernel_exp_action_interference_h100.json"))
    with open(path, "w") as f:
        json.dump(out, f, indent=1)
    ck = out["clocks"]

    def mhz(arch, name):
        c = ck.get(f"{arch}:{name}")
        return f"{c['sm_mhz']:.0f}/{c['power_w']:.0f}" if c else "-"

    print(f"\nVLM b={B} + action b={B}, ms p50. 'in lockstep' = each stage's own span inside the lockstep; "
          "clock = median SM MHz / W over the phase")
    print(f"{'model':>10} {'L':>4} {'variant':>13} {'VLM alone':>9} {'act alone':>9} {'VLM in':>7} {'act in':>7} "
          f"{'lockstep':>8} {'clock (lock)':>13}")
    for res in out["models"]:
        m, a = res["median_ms"], res["arch"]
        print(f"{a:>10} {'full':>4} {'alone':>13} {m['vlm_alone_full']:>9.2f} {m['act_alone_full']:>9.2f} "
              f"{'':>7} {'':>7} {m['vlm_alone_full'] + m['act_alone_full']:>8.2f} {mhz(a, 'act_alone_full'):>13}")
        for lv in res["levels"]:
            for name in ("guarded", "guarded_plan", "part", "part_tri"):
                lock = m[f"lock_{name}_{lv}"]
                va = m.get(f"vlm_alone_{'part' if name.startswith('part') else 'guarded'}_{lv}", float("nan"))
                aa = m.get(f"act_alone_{name}_{lv}", m["act_alone_full"])
                print(f"{a:>10} {lv:>4} {name:>13} {va:>9.2f} {aa:>9.2f} {lock['vlm']:>7.2f} {lock['action']:>7.2f} "
                      f"{lock['lockstep']:>8.2f} {mhz(a, f'lock_{name}_{lv}'):>13}")


if __name__ == "__main__":
    main()
