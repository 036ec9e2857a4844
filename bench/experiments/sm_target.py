"""Experiment: capture each restricted VLM graph with cuBLAS told how many SMs it will get.

A VLM graph captured on a green context of n SMs runs on n SMs, but cuBLAS picks its GEMM
kernels for the whole GPU (its heuristic reads the device's SM count). A tile grid sized for
one wave on 132 SMs takes two waves on 128. cuBLAS can plan for a smaller SM count
(``cublasSetSmCountTarget``, or ``CUBLASLT_MATMUL_DESC_SM_COUNT_TARGET`` on cuBLASLt's matmul
descriptor), which torch sets from ``torch._C._set_sm_carveout_experimental`` on every GEMM
call. A captured graph keeps the kernels chosen at capture, so setting the target while
capturing is enough. Main captures restricted VLM graphs the ``lt+target`` way
(``services.executor.graphs.gemm_sm_target``); this script compares it with the others.

For each zoo model at batch 2 (the lockstep that dominates E1) and each SM level, the VLM
graph at that level is captured in each of these ways (graphs, runner and lockstep timer are
the engine's own):
  plain      cuBLAS as torch calls it by default (main before gemm_sm_target);
  target     cuBLAS with the SM-count target set to the level;
  lt         every GEMM through cuBLASLt (``preferred_blas_library("cublaslt")``), no target;
  lt+target  cuBLASLt with the target: what main does now.
Two more lockstep variants use the plain VLM graph:
  act-target the action graph captured with the target (cuBLAS, and the SM count the Triton
             kernels size their grids by) set to the SMs the level leaves free;
  prio       launched from an action stream of the highest priority and a VLM stream of the
             lowest (also unrestricted: ``lock_prio_none``).
Reported: the VLM alone on its level, and the whole lockstep (VLM b=2 on the level beside the
action stage b=2), medians over interleaved rounds; the stages alone on the whole GPU; and
the unrestricted VLM through cuBLASLt (``vlm_alone_full_lt``).

    OUT=/tmp python bench/experiments/sm_target.py
    MODELS=pi0,xr0 LEVELS=80,104,120 ROUNDS=2 OUT=/tmp python bench/experiments/sm_target.py
    PROFILE=pi0:128,96 OUT=/tmp python bench/experiments/sm_target.py   # kernel times by level
    PROFILE=pi0:128,96 LT=1 OUT=/tmp python bench/experiments/sm_target.py   # the same, cuBLASLt + target
"""

from __future__ import annotations

import contextlib
import datetime
import gc
import json
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from bench.experiments.timing import replay_ms  # noqa: E402
from services.executor.graphs import GraphPools, GraphStages  # noqa: E402
from services.executor.lockstep import CudaRunner  # noqa: E402
from services.executor.profiler import time_lockstep  # noqa: E402
from services.executor.sm import GreenStreams, sm_count  # noqa: E402
from shared.models import build_model, fused  # noqa: E402

B = 2
CAPTURES = {"plain": (False, False), "target": (False, True), "lt": (True, False), "lt+target": (True, True)}
VARIANTS = (*CAPTURES, "act-target", "prio")


@contextlib.contextmanager
def sm_target(device: torch.device, sms: int | None, triton: bool = False, lt: bool = False):
    """cuBLAS (and with ``triton`` the fused kernels' grid sizing) target ``sms`` SMs inside
    (None: no target); with ``lt`` every GEMM goes through cuBLASLt."""
    blas = torch.backends.cuda.preferred_blas_library()
    idx = device.index or 0
    saved = fused._SM_COUNT.get(idx)
    if lt:
        torch.backends.cuda.preferred_blas_library("cublaslt")
    if sms is not None:
        torch._C._set_sm_carveout_experimental(sm_count(device) - sms)
        if triton:
            fused._SM_COUNT[idx] = sms
    try:
        yield
    finally:
        torch._C._set_sm_carveout_experimental(None)
        torch.backends.cuda.preferred_blas_library(blas)
        if triton and sms is not None:
            if saved is None:
                fused._SM_COUNT.pop(idx, None)
            else:
                fused._SM_COUNT[idx] = saved


def capture_vlm(st: GraphStages, level: int | None, lt: bool, target: bool) -> torch.cuda.CUDAGraph:
    """The VLM graph on ``level``'s stream, captured directly (``GraphStages.capture_vlm``
    would apply main's own target on top)."""
    stream = st._stream(level)
    with sm_target(st.device, level if target else None, lt=lt):
        return st._capture(lambda: st._vlm_body(B), stream, st.pools.vlm)


def capture_action(st: GraphStages, target: int | None) -> torch.cuda.CUDAGraph:
    with sm_target(st.device, target, triton=True):
        return st._capture(lambda: st._action_body(B), st.action_stream, st.pools.action)


def run_model(arch: str, device: torch.device, levels: list[int], rounds: int, repeats: int) -> dict:
    t0 = time.perf_counter()
    model = build_model(arch, "full", device=device)
    total = sm_count(device)
    runner = CudaRunner(device)
    green = GreenStreams(device, levels)
    runner.green = green
    # The same runner with the action stream at the highest priority and the VLM's at the
    # lowest: a graph's kernels take the priority of the stream it is launched into.
    low, high = torch.cuda.Stream.priority_range()
    prio = CudaRunner(device)
    prio.green = green
    prio.vlm_stream = torch.cuda.Stream(device, priority=low)
    prio.action_stream = torch.cuda.Stream(device, priority=high)
    st = GraphStages(model, device, [B], 0, GraphPools.create(), green, runner.vlm_stream, runner.action_stream)
    st.allocate()
    vlm_full = capture_vlm(st, None, False, False)
    vlm_full_lt = capture_vlm(st, None, True, False)
    act_full = capture_action(st, None)
    vlm = {(name, lv): capture_vlm(st, lv, lt, target) for name, (lt, target) in CAPTURES.items() for lv in levels}
    act_target = {lv: capture_action(st, total - lv) for lv in levels}
    built_s = time.perf_counter() - t0

    def use(level, vlm_graph, act_graph) -> None:
        st.vlm_graphs[(B, level)] = vlm_graph
        st.action_graphs[B] = act_graph

    samples: dict[str, list[float]] = {}
    for _ in range(rounds):
        samples.setdefault("vlm_alone_full", []).extend(replay_ms(vlm_full, runner.vlm_stream, repeats))
        samples.setdefault("act_alone_full", []).extend(replay_ms(act_full, runner.action_stream, repeats))
        samples.setdefault("vlm_alone_full_lt", []).extend(replay_ms(vlm_full_lt, runner.vlm_stream, repeats))
        use(None, vlm_full, act_full)
        samples.setdefault("lock_none", []).append(time_lockstep(runner, st, B, st, B, None, repeats, warmup=3))
        samples.setdefault("lock_prio_none", []).append(time_lockstep(prio, st, B, st, B, None, repeats, warmup=3))
        for lv in levels:
            for variant in VARIANTS:
                vg = vlm[(variant if variant in CAPTURES else "plain", lv)]
                use(lv, vg, act_target[lv] if variant == "act-target" else act_full)
                if variant in CAPTURES:
                    samples.setdefault(f"vlm_alone_{variant}_{lv}", []).extend(
                        replay_ms(vg, runner.vlm_stream, repeats))
                samples.setdefault(f"lock_{variant}_{lv}", []).append(
                    time_lockstep(prio if variant == "prio" else runner, st, B, st, B, lv, repeats, warmup=3))
    med = {k: round(statistics.median(v), 3) for k, v in samples.items()}
    back_to_back = med["vlm_alone_full"] + med["act_alone_full"]
    best = {}
    for variant in VARIANTS:
        lv = min(levels, key=lambda x: med[f"lock_{variant}_{x}"])
        best[variant] = {"level": lv, "ms": med[f"lock_{variant}_{lv}"],
                         "gain_vs_back_to_back": round(back_to_back / med[f"lock_{variant}_{lv}"], 3)}
    return {"arch": arch, "levels": levels, "rounds": rounds, "repeats": repeats, "built_s": round(built_s, 1),
            "median_ms": med, "back_to_back_ms": round(back_to_back, 3),
            "bound": round(back_to_back / max(med["vlm_alone_full"], med["act_alone_full"]), 3),
            "best": best, "samples": samples}


def profile_levels(arch: str, device: torch.device, levels: list[int], runs: int = 3, lt: bool = False) -> dict:
    """Kernel time of one eager VLM call at batch 2 on the whole GPU and on each level's green
    stream (eager kernels launched there are restricted like a captured graph's), by kernel name."""
    model = build_model(arch, "full", device=device)
    gen = torch.Generator().manual_seed(1234)
    images, state, tokens = model.example_inputs(B, device=device, generator=gen)
    green = GreenStreams(device, levels)
    per_level: dict[str, dict[str, float]] = {}
    for level in [None, *levels]:
        stream = torch.cuda.Stream(device) if level is None else green.stream(level)
        stream.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(stream), sm_target(device, level if lt else None, lt=lt):
            for _ in range(3):
                model.vlm_stage(images, state, tokens)
            stream.synchronize()
            with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
                for _ in range(runs):
                    model.vlm_stage(images, state, tokens)
                stream.synchronize()
        kernels: dict[str, float] = {}
        for evt in prof.key_averages():
            if evt.device_type == torch.autograd.DeviceType.CUDA and evt.self_device_time_total > 0:
                kernels[evt.key] = kernels.get(evt.key, 0.0) + evt.self_device_time_total / runs / 1e3
        per_level["none" if level is None else str(level)] = kernels
    full = per_level["none"]
    names = sorted(set().union(*per_level.values()),
                   key=lambda k: -(per_level[str(levels[0])].get(k, 0.0) - full.get(k, 0.0)))
    print(f"\n{arch} VLM b={B}{' (cuBLASLt, SM target = level)' if lt else ''}, eager kernel ms per call by level "
          "(largest growth first)")
    print(f"{'kernel':>60} {'full':>7} " + " ".join(f"{lv:>7}" for lv in levels))
    print(f"{'all kernels':>60} {sum(full.values()):>7.3f} "
          + " ".join(f"{sum(per_level[str(lv)].values()):>7.3f}" for lv in levels))
    for name in names[:15]:
        print(f"{name[:60]:>60} {full.get(name, 0.0):>7.3f} "
              + " ".join(f"{per_level[str(lv)].get(name, 0.0):>7.3f}" for lv in levels))
    return {"arch": arch, "levels": levels, "runs": runs, "cublaslt_target": lt, "kernel_ms": per_level}


def main() -> None:
    device = torch.device("cuda", 0)
    torch.cuda.set_device(device)
    if os.environ.get("PROFILE"):  # e.g. PROFILE=pi0:128,96
        arch, _, lv = os.environ["PROFILE"].partition(":")
        lt = os.environ.get("LT") == "1"
        res = profile_levels(arch, device, [int(x) for x in lv.split(",")], lt=lt)
        name = f"kernel_exp_sm_profile_{arch}{'_lt' if lt else ''}.json"
        path = os.path.join(os.environ.get("OUT", "."), os.environ.get("OUT_NAME", name))
        with open(path, "w") as f:
            json.dump(res, f, indent=1)
        return
    models = os.environ.get("MODELS", "pi0,smolvla,groot_n15,xr0").split(",")
    levels = [int(x) for x in os.environ.get("LEVELS", "56,64,72,80,88,96,104,112,120,128").split(",")]
    rounds = int(os.environ.get("ROUNDS", "3"))
    repeats = int(os.environ.get("REPEATS", "12"))
    out = {"experiment": "sm_target", "gpu": torch.cuda.get_device_name(device), "torch": torch.__version__,
           "date": datetime.date.today().isoformat(), "commit": os.environ.get("ROBION_COMMIT", "unknown"),
           "batch": B, "models": []}
    for arch in models:
        res = run_model(arch, device, levels, rounds, repeats)
        out["models"].append(res)
        gc.collect()
        torch.cuda.empty_cache()  # the model's weights and graphs go before the next is built
        print(f"{arch}: built in {res['built_s']} s; back to back {res['back_to_back_ms']} ms, "
              f"unrestricted lockstep {res['median_ms']['lock_none']} ms", flush=True)
    path = os.path.join(os.environ.get("OUT", "."), os.environ.get("OUT_NAME", "kernel_exp_sm_target_h100.json"))
    with open(path, "w") as f:
        json.dump(out, f, indent=1)
    print(f"\nlockstep VLM b={B} + action b={B}, ms p50; VLM alone on the level, then the lockstep, per variant")
    head = " ".join(f"{v:>10}" for v in CAPTURES) + " | " + " ".join(f"{v:>10}" for v in VARIANTS)
    print(f"{'model':>10} {'SMs':>4} {head}")
    for res in out["models"]:
        m = res["median_ms"]
        for lv in res["levels"]:
            print(f"{res['arch']:>10} {lv:>4} " + " ".join(f"{m[f'vlm_alone_{v}_{lv}']:>10.2f}" for v in CAPTURES)
                  + " | " + " ".join(f"{m[f'lock_{v}_{lv}']:>10.2f}" for v in VARIANTS))
        print(f"{res['arch']:>10} full: VLM {m['vlm_alone_full']:.2f} (cuBLASLt {m['vlm_alone_full_lt']:.2f}), "
              f"action {m['act_alone_full']:.2f}, back to back {res['back_to_back_ms']:.2f}, "
              f"unrestricted lockstep {m['lock_none']:.2f} (prio {m['lock_prio_none']:.2f}), bound {res['bound']}x")
        print(f"{'':>10} best: " + ", ".join(f"{v} {b['ms']:.2f} @{b['level']} ({b['gain_vs_back_to_back']}x)"
                                            for v, b in res["best"].items()))


if __name__ == "__main__":
    main()
