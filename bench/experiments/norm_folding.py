"""Experiment (not on main): RMSNorm folded into the action experts' QKV and gate/up GEMMs.

Needs the changes in norm_folding.patch (fused.py: split-K and prescaled weights for the
norm GEMM kernels; layers.py, pi0.py, smolvla.py: ``fold_norms``; the GPU kernel tests):

    git apply bench/experiments/norm_folding.patch
    OUT=/tmp MICRO=1 python bench/experiments/norm_folding.py

With ``fold_norms`` set on pi0 or SmolVLA, each expert layer replaces norm + QKV GEMM +
QKV split with ``fused.norm_qkv`` and norm + gate/up GEMM + gated activation with
``fused.norm_gated_mlp_in``: 9 launches per layer-step become 5. The norm weights are
multiplied into the weights' columns once per stage call (``DecoderLayer.folded_weights``),
so the kernels apply only 1/rms and their A tile goes to the dot unchanged. Applying the norm
weight to the A tile inside the kernel (the first version of these kernels) cost about
5 us a call; ``MICRO=1`` times that too.

Per model and batch: one VLM graph and three action graphs on the same handoff: main,
folded with one program per output tile (``GEMM_CFG["norm_split"] = 1``), and folded
with split-K to about one program per SM (the partial sums and sums of squares reduced by
the last program of each tile). Replayed in rotating rounds; p50 of the action stage and
of VLM + action; outputs compared with main's (the norm weights are randomised so that the
fold is exercised).

    MODELS=smolvla BATCHES=1,2 ROUNDS=4 REPS=50 OUT=/tmp python bench/experiments/norm_folding.py

Results: docs/RESULTS.md (model zoo, "Tried and not kept", item 6); raw JSON
bench/results/kernel_exp_norm_folding_h100.json, kernel tables
bench/results/kernel_exp_norm_folding_profile_b1_h100.txt.
"""
from __future__ import annotations

import datetime
import json
import os
import statistics
import subprocess
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from bench.experiments.timing import replay_ms, replay_pair_ms  # noqa: E402
from shared.models import build_model, fused  # noqa: E402
from shared.models.layers import RMSNorm  # noqa: E402

OUT = os.environ.get("OUT", "/tmp")
MODELS = os.environ.get("MODELS", "smolvla,pi0").split(",")
BATCHES = [int(b) for b in os.environ.get("BATCHES", "1,2,4").split(",")]
ROUNDS = int(os.environ.get("ROUNDS", "4"))
REPS = int(os.environ.get("REPS", "50"))
MICRO = os.environ.get("MICRO")  # set: also time the gate/up GEMM alone, with and without the norm
PROFILE = os.environ.get("PROFILE")  # a path: kernel tables of each variant's eager action stage (first batch)


def set_fold(model, on: bool) -> int:
    """Set the model's ``fold_norms``; returns the number of action layers it folds."""
    model.fold_norms = on
    return sum(1 for m in getattr(model, model.ACTION_MODULES[0]).modules() if hasattr(m, "folded_weights"))


def run(arch: str, batch: int) -> dict:
    dev = torch.device("cuda")
    model = build_model(arch, "full", seed=0, device=dev)
    gen = torch.Generator(device="cpu").manual_seed(7)
    with torch.no_grad():
        for name in model.ACTION_MODULES:  # random norm weights: ones would hide a wrong fold
            for m in getattr(model, name).modules():
                if isinstance(m, RMSNorm):
                    m.weight.copy_(1 + 0.2 * torch.randn(m.weight.shape, generator=gen))
    images, state, tokens = model.example_inputs(batch, device=dev, generator=torch.Generator().manual_seed(batch))
    tokens[:, model.io.prompt_len // 2:] = 0
    noise = model.noise(batch, device=dev, generator=torch.Generator().manual_seed(99)).to(torch.bfloat16)
    layers = set_fold(model, False)
    variants = {"main": (False, None), "folded": (True, 1), "folded_splitk": (True, None)}

    def use(name: str) -> None:
        on, split = variants[name]
        set_fold(model, on)
        fused.GEMM_CFG["norm_split"] = split

    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side), torch.no_grad():
        handoff = model.vlm_stage(images, state, tokens)
        for name in variants:  # Triton JIT and cuBLAS heuristics for every variant
            use(name)
            for _ in range(2):
                model.action_stage(handoff, noise)
    torch.cuda.current_stream().wait_stream(side)
    torch.cuda.synchronize()

    pool = torch.cuda.graph_pool_handle()
    g_vlm = torch.cuda.CUDAGraph()
    with torch.no_grad(), torch.cuda.graph(g_vlm, pool=pool):
        handoff = model.vlm_stage(images, state, tokens)
    graphs, outs = {}, {}
    for name in variants:
        use(name)
        g = torch.cuda.CUDAGraph()
        with torch.no_grad(), torch.cuda.graph(g, pool=pool):
            outs[name] = model.action_stage(handoff, noise)
        graphs[name] = g
    use("main")
    got = {}
    for name in variants:  # read each output right after its replay: graphs sharing a pool reuse
        g_vlm.replay()     # each other's freed intermediates, so a later replay may overwrite it
        graphs[name].replay()
        torch.cuda.synchronize()
        got[name] = outs[name].float().clone()
    ref = got["main"]
    if PROFILE and batch == BATCHES[0]:
        acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
        with open(PROFILE, "a") as f, torch.no_grad():
            for name in variants:
                use(name)
                with torch.profiler.profile(activities=acts) as prof:
                    model.action_stage(handoff, noise)
                    torch.cuda.synchronize()
                kernels = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
                f.write(f"\n## {arch} action stage, batch {batch}, {name}: {len(kernels)} kernels, "
                        f"{sum(e.device_time for e in kernels) / 1000:.3f} ms of kernel time\n")
                f.write(prof.key_averages().table(sort_by="device_time_total", row_limit=14, max_name_column_width=60))
        use("main")
    res = {"arch": arch, "batch": batch, "fold_layers": layers}
    act: dict[str, list[float]] = {n: [] for n in variants}
    both: dict[str, list[float]] = {n: [] for n in variants}
    names = list(variants)
    for r in range(ROUNDS):
        for name in names[r % 3:] + names[:r % 3]:
            _, a, t = replay_pair_ms(g_vlm, graphs[name], REPS)
            act[name] += a
            both[name] += t
    for name in variants:
        res[name] = {"action_p50": statistics.median(act[name]),
                     "action_p99": sorted(act[name])[int(0.99 * (len(act[name]) - 1))],
                     "vla_p50": statistics.median(both[name]),
                     "rel_diff_vs_main": ((got[name] - ref).norm() / ref.norm()).item()}
    del graphs, g_vlm
    torch.cuda.empty_cache()
    return res


def micro() -> list[dict]:
    """Microseconds per call of SmolVLA's and pi0's gate/up (batch 1) in a graph of 16 calls on
    distinct weights (streamed from HBM): cuBLAS + norm + activation as main runs it, and the
    folded kernel with the norm in the A tile, without a norm (the A tile straight to the dot),
    one program per tile or split-K."""
    from shared.models.fused import Workspace, gated_act, norm_gated_mlp_in

    dev = torch.device("cuda")
    rows_out = []
    for name, rows, k, f, act in (("smolvla", 50, 720, 2048, "silu"), ("pi0", 51, 1024, 4096, "gelu_tanh")):
        g = torch.Generator(device="cuda").manual_seed(0)
        x = torch.randn(1, rows, k, device=dev, generator=g).bfloat16()
        nw = (torch.rand(k, device=dev, generator=g) + 0.5).bfloat16()
        ws_ = [(torch.randn(2 * f, k, device=dev, generator=g) / k ** 0.5).bfloat16() for _ in range(16)]
        ws = Workspace(dev)
        norm = torch.nn.functional.rms_norm

        def main_path():
            for w in ws_:
                gated_act(torch.nn.functional.linear(norm(x, (k,), nw, 1e-6), w), act)

        folded = [fused.fold_norm_weight(w, nw) for w in ws_]
        cases = {"main": (main_path, None)}
        for label, norm_w in (("norm", nw), ("no_norm", None)):
            for split in (1, None):
                cases[f"{label}_split{split or 'auto'}"] = (
                    lambda norm_w=norm_w: [norm_gated_mlp_in(x, norm_w, 1e-6, w, act, ws) for w in ws_], split)
        for split in (1, None):  # the norm weight in the weight's columns: only 1/rms in the kernel
            cases[f"prescaled_split{split or 'auto'}"] = (
                lambda: [norm_gated_mlp_in(x, None, 1e-6, w, act, ws, prescaled=True) for w in folded], split)
        res = {"model": name, "rows": rows, "k": k, "f": f}
        for label, (fn, split) in cases.items():
            fused.GEMM_CFG["norm_split"] = split
            s = torch.cuda.Stream()
            s.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(s):
                fn()
            s.synchronize()
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph, stream=s):
                fn()
            res[label] = statistics.median(replay_ms(graph, s, 30)) * 1000 / len(ws_)
        fused.GEMM_CFG["norm_split"] = None
        rows_out.append(res)
        print(" ".join(f"{k_}={v:.2f}" if isinstance(v, float) else f"{k_}={v}" for k_, v in res.items()))
    return rows_out


def main() -> None:
    commit = os.environ.get("ROBION_COMMIT") or subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    micro_rows = micro() if MICRO else []
    rows = [run(arch, b) for arch in MODELS for b in BATCHES]
    doc = {"micro_us": micro_rows, "gpu": torch.cuda.get_device_name(), "torch": torch.__version__, "commit": commit,
           "date": datetime.date.today().isoformat(), "rounds": ROUNDS, "reps": REPS, "rows": rows}
    with open(os.path.join(OUT, "kernel_exp_norm_folding_h100.json"), "w") as f:
        json.dump(doc, f, indent=1)
    print(f"{'model':8} {'b':>2} | action p50: {'main':>6} {'folded':>7} {'split-K':>7} | VLA p50: {'main':>6} "
          f"{'folded':>7} {'split-K':>7} | rel diff split-K")
    for r in rows:
        m, f, k = r["main"], r["folded"], r["folded_splitk"]
        print(f"{r['arch']:8} {r['batch']:>2} | {m['action_p50']:18.3f} {f['action_p50']:7.3f} {k['action_p50']:7.3f} | "
              f"{m['vla_p50']:15.3f} {f['vla_p50']:7.3f} {k['vla_p50']:7.3f} | {k['rel_diff_vs_main']:.2e}")

if __name__ == "__main__":
    main()
