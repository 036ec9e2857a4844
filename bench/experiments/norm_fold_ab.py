"""Experiment: the action stages with the RMSNorms folded away against the same stages with
their norm kernels, side by side in one process.

Folded (main): the split-K residual GEMM leaves each row's sums of squares, the next QKV or
gate/up GEMM runs on the un-normalised rows with the norm weight folded into its weight, and
the QKV split or the gated activation applies 1 / rms (``layers.folded_norm_linear``). Unfolded:
``layers.FOLD_NORMS = False``, the path before that change (a norm kernel before each GEMM).
Over 64 rows (batch 2), the split-K GEMM takes weights under 4 MB (SmolVLA) only when the
norm after it folds; a third variant keeps the old rule (weights >= 4 MB only), so SmolVLA's
batch-2 norms stay unfolded. The action graphs read the same VLM
handoff and are replayed in turn.

    OUT=/tmp python bench/experiments/norm_fold_ab.py
    MODELS=pi0 BATCHES=1 ITERS=100 OUT=/tmp python bench/experiments/norm_fold_ab.py

Prints a table last and writes ``norm_fold_ab_<gpu>.json`` (or OUT_NAME) under OUT.
"""
from __future__ import annotations

import json
import os
import statistics
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from shared.models import build_model, fused, layers  # noqa: E402

from timing import (alternating_ms, capture_checked, env_settings, pct, result_header, save_result,  # noqa: E402
                    seeded_inputs)


def kernels_in(graph_body) -> int:
    """Kernel launches of one eager call (profiler), the number the graph replays."""
    from torch.profiler import ProfilerActivity, profile
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        graph_body()
        torch.cuda.synchronize()
    return sum(e.count for e in prof.key_averages() if e.device_type == torch.autograd.DeviceType.CUDA
               and "memcpy" not in e.key.lower() and "memset" not in e.key.lower())


def run_model(arch: str, batches: list[int], iters: int) -> dict:
    dev = torch.device("cuda")
    model = build_model(arch, "full", device=dev, seed=0)
    with torch.no_grad():  # random norm weights, so that folding them is not a no-op
        g = torch.Generator(device="cpu").manual_seed(7)
        for mod in model.modules():
            if isinstance(mod, layers.RMSNorm):
                mod.weight.copy_((1 + 0.3 * torch.randn(mod.weight.shape, generator=g)).to(mod.weight.dtype))
    out = {}
    for b in batches:
        images, state, tokens, noise = seeded_inputs(model, b, dev, half_prompt=True)
        graphs, outs, counts = {}, {}, {}
        pool = torch.cuda.graph_pool_handle()
        with torch.inference_mode():
            hand = model.vlm_stage(images, state, tokens)
            hand = {k: v.clone() for k, v in hand.items()}
            variants = [("unfolded", False, True), ("folded", True, True)]
            if b > 1:  # the split-K GEMM over 64 rows only for weights >= 4 MB, as without folding
                variants.append(("folded_big_weights_only", True, False))
            for name, fold, small in variants:
                layers.FOLD_NORMS = fold
                fused.GEMM_CFG["stats_over_64_rows"] = small
                # Warm-up (Triton JIT, cuBLAS heuristics, folded weights), capture, one replay.
                graphs[name], *outs[name] = capture_checked(lambda: model.action_stage(hand, noise), pool, warmup=3)
                counts[name] = kernels_in(lambda: model.action_stage(hand, noise))
            layers.FOLD_NORMS = True
            fused.GEMM_CFG["stats_over_64_rows"] = True
        times = alternating_ms(graphs, iters)
        ref = outs["unfolded"][1]
        row = {}
        for name in graphs:
            eager, graphed = outs[name]
            row[name] = {"p50_ms": statistics.median(times[name]), "p99_ms": pct(times[name], 0.99),
                         "kernels": counts[name],
                         "rel_err_vs_unfolded": float((graphed - ref).norm() / ref.norm()),
                         "graph_vs_eager_max_abs": float((graphed - eager).abs().max()),
                         "finite": bool(torch.isfinite(graphed).all())}
        out[b] = row
        print(arch, b, json.dumps(row))
        del graphs
        torch.cuda.empty_cache()
    return out


def main():
    models, batches, iters = env_settings("pi0,smolvla", "1,2")
    res = {**result_header(iters), "models": {m: run_model(m, batches, iters) for m in models}}
    save_result(res, "norm_fold_ab")
    print(f"\naction stage, norms folded vs unfolded, {iters} alternating replays each ({res['gpu']})")
    print(f"{'model':8s} {'b':>2s} {'unfolded p50':>13s} {'folded p50':>11s} {'p99 u/f':>14s} {'kernels u/f':>12s}"
          f" {'rel err':>8s} {'graph-eager':>11s} variant")
    for m, rows in res["models"].items():
        for b, r in rows.items():
            u = r["unfolded"]
            for name in [n for n in r if n != "unfolded"]:
                f = r[name]
                print(f"{m:8s} {b:2d} {u['p50_ms']:13.3f} {f['p50_ms']:11.3f} {u['p99_ms']:6.3f}/{f['p99_ms']:6.3f}"
                      f" {u['kernels']:5d}/{f['kernels']:5d} {f['rel_err_vs_unfolded']:8.1e}"
                      f" {f['graph_vs_eager_max_abs']:11.1e} {name}")


if __name__ == "__main__":
    main()
