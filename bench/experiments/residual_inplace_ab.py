"""Experiment: the residual projections of the VLM stages (and of GR00T's VL adapter) accumulating
into the residual in place on cuBLAS, against ``addmm`` into a copy of it, side by side in one process.

``torch.addmm(residual, x, w.t())`` first copies the residual into its output (a DtoD copy), then
runs the GEMM with beta = 1. Every pre-norm block ends its attention and its MLP that way, so a VLM
made of N blocks makes 2N such copies per call: XR0's 27 ViT blocks and 36 LM layers, pi0's 27 + 18.
``layers.linear_residual`` now passes ``inplace`` (``residual.addmm_``): same GEMM, no copy; so does
the split-K GEMM's cuBLAS fallback, which pi0's and SmolVLA's action stages take at batch 4 (200 rows).
"copy" here is both as they were before (a copy, except GR00T's DiT over 64 rows, already in place).

    OUT=/tmp python bench/experiments/residual_inplace_ab.py
    MODELS=xr0 BATCHES=2 ITERS=100 OUT=/tmp python bench/experiments/residual_inplace_ab.py

Prints a table last and writes ``residual_inplace_ab_<gpu>.json`` (or OUT_NAME) under OUT.
"""
from __future__ import annotations

import json
import os
import statistics
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from shared.models import build_model, fused, layers, smolvla  # noqa: E402
from shared.models.fused import addmm_residual, linear_residual_splitk  # noqa: E402

from timing import (alternating_ms, capture_checked, env_settings, pct, result_header, save_result,  # noqa: E402
                    seeded_inputs)

INPLACE = layers.linear_residual


def copying_linear_residual(x, lin, residual, ws=None):
    """``layers.linear_residual`` before this change: ``addmm`` into a copy unless the action
    stage's workspace is given and the call has over 64 rows."""
    if ws is None:
        return addmm_residual(x, lin.weight, lin.bias, residual)
    if residual.numel() // lin.out_features <= 64:
        return linear_residual_splitk(x, lin.weight, lin.bias, residual, ws)
    out = addmm_residual(x, lin.weight, lin.bias, residual, inplace=residual.is_contiguous())
    ws.keep_stats(out, None)
    return out


def copying_addmm_residual(x, weight, bias, residual, inplace=False):
    """``fused.addmm_residual`` as the split-K GEMM's cuBLAS fallback called it before: into a copy."""
    return addmm_residual(x, weight, bias, residual)


def use(mode: str) -> None:
    copy = mode == "copy"
    layers.linear_residual = smolvla.linear_residual = copying_linear_residual if copy else INPLACE
    fused.addmm_residual = copying_addmm_residual if copy else addmm_residual


def copies_in(body) -> tuple[int, int]:
    """(kernels, DtoD copies) of one eager call, from the profiler."""
    from torch.profiler import ProfilerActivity, profile
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        body()
        torch.cuda.synchronize()
    cuda = [e for e in prof.key_averages() if e.device_type == torch.autograd.DeviceType.CUDA]
    copies = sum(e.count for e in cuda if "memcpy" in e.key.lower() and "dtod" in e.key.lower())
    kernels = sum(e.count for e in cuda if "memcpy" not in e.key.lower() and "memset" not in e.key.lower())
    return kernels, copies


def run_model(arch: str, batches: list[int], iters: int) -> dict:
    dev = torch.device("cuda")
    model = build_model(arch, "full", device=dev, seed=0)
    out = {}
    for b in batches:
        images, state, tokens, noise = seeded_inputs(model, b, dev)
        row: dict = {}
        with torch.inference_mode():
            for stage in ("vlm", "action"):
                graphs, outs, counts = {}, {}, {}
                pool = torch.cuda.graph_pool_handle()
                hand = {k: v.clone() for k, v in model.vlm_stage(images, state, tokens).items()}
                body = ((lambda: model.vlm_stage(images, state, tokens)) if stage == "vlm"
                        else (lambda: model.action_stage(hand, noise)))
                for name in ("copy", "inplace"):
                    use(name)
                    graphs[name], *outs[name] = capture_checked(body, pool, warmup=3)
                    counts[name] = copies_in(body)
                use("inplace")
                times = alternating_ms(graphs, iters)

                def diff(a, b):
                    if isinstance(a, dict):
                        return max(float((a[k] - b[k]).abs().max()) for k in a)
                    return float((a - b).abs().max())
                row[stage] = {name: {"p50_ms": statistics.median(times[name]), "p99_ms": pct(times[name], 0.99),
                                     "kernels": counts[name][0], "dtod_copies": counts[name][1],
                                     "max_abs_vs_copy": diff(outs[name][1], outs["copy"][1]),
                                     "graph_vs_eager_max_abs": diff(outs[name][1], outs[name][0])}
                              for name in graphs}
                graphs.clear()
        print(arch, b, json.dumps(row), flush=True)
        out[b] = row
    return out


def main():
    models, batches, iters = env_settings("pi0,smolvla,groot_n15,xr0", "1,2,4")
    res = result_header(iters)
    for m in models:
        res[m] = run_model(m, batches, iters)
        torch.cuda.empty_cache()  # the model is gone with run_model's frame
    save_result(res, "residual_inplace_ab")
    print(f"\nResidual projections in place vs into a copy, p50 ms (p99), {iters} alternating replays ({res['gpu']})")
    for m in models:
        for b, r in res[m].items():
            for stage in ("vlm", "action"):
                c, i = r[stage]["copy"], r[stage]["inplace"]
                print(f"  {m:10s} b={b} {stage:6s} copy {c['p50_ms']:.3f} ({c['p99_ms']:.3f}) {c['dtod_copies']:3d} copies"
                      f"   inplace {i['p50_ms']:.3f} ({i['p99_ms']:.3f}) {i['dtod_copies']:3d} copies"
                      f"   max|diff| {i['max_abs_vs_copy']:.1e}   graph-eager {i['graph_vs_eager_max_abs']:.1e}")


if __name__ == "__main__":
    main()
