"""Experiment: a VLM's prefix attention as two cuBLAS GEMMs around a row softmax
(``fused.gemm_attention``) against the library flash kernel that SDPA picks (cuDNN on the H100).

pi0's Gemma runs its 8 query heads on one KV head: folded, that is 4480 query rows per image pair
over 560 keys with D = 256, which cuDNN covers with about 35 programs (39 us a call, 17 calls).
The GEMM form spreads the two products over the whole GPU and keeps the scores in fp32.

Part 1 times the attention call alone on pi0's shapes (a graph of 17 calls) and checks it
against float64. Part 2 captures each model's whole VLM stage twice, the GEMM form off (main)
and on, and replays the two graphs in turn.

    OUT=/tmp python bench/experiments/prefix_attention.py
    MODELS=pi0 BATCHES=1 ITERS=100 OUT=/tmp python bench/experiments/prefix_attention.py

Prints a table last and writes ``prefix_attention_<gpu>.json`` (or OUT_NAME) under OUT.
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


def set_gemm(on: bool, max_heads: int = 64) -> None:
    fused.ATTN_CFG["gemm"] = on
    fused.ATTN_CFG["gemm_max_heads"] = max_heads


def rel(a: dict, b: dict) -> float:
    return max(float((a[k] - b[k]).norm() / b[k].norm().clamp_min(1e-30)) for k in b)


def micro(iters: int) -> dict:
    """pi0's Gemma prefix attention alone: 560 tokens (24 of them padding), 8 query heads, 1 KV head."""
    dev, res = torch.device("cuda"), {}
    for b in (1, 2):
        g = torch.Generator(device="cpu").manual_seed(b)
        q = torch.randn(b, 560, 8, 256, generator=g).to(dev, torch.bfloat16)
        k = torch.randn(b, 1, 560, 256, generator=g).to(dev, torch.bfloat16)
        v = torch.randn(b, 1, 560, 256, generator=g).to(dev, torch.bfloat16)
        mask = torch.ones(b, 560, dtype=torch.bool, device=dev)
        mask[:, -24:] = False
        bias = layers.attn_bias(mask[:, None, :], 1, torch.bfloat16)
        qh = q.double().reshape(b, 560 * 8, 1, 256).transpose(1, 2)
        ref = torch.softmax(qh @ k.double().transpose(-1, -2) / 16 + bias.double(), -1) @ v.double()
        ref = ref.transpose(1, 2).reshape(b, 560, 8 * 256)
        graphs, errs = {}, {}
        for name, on in (("sdpa", False), ("gemm", True)):
            set_gemm(on)
            for _ in range(2):
                out = layers.attention(q, k, v, bias)
            torch.cuda.synchronize()
            errs[name] = float((out.double() - ref).norm() / ref.norm())
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                for _ in range(17):
                    layers.attention(q, k, v, bias)
            graphs[name] = graph
        set_gemm(False)
        times = alternating_ms(graphs, iters)
        res[b] = {n: {"us_per_call_p50": statistics.median(times[n]) * 1000 / 17,
                      "us_per_call_p99": pct(times[n], 0.99) * 1000 / 17, "rel_err_vs_fp64": errs[n]}
                  for n in graphs}
        print("micro", b, json.dumps(res[b]))
    return res


def run_model(arch: str, batches: list[int], iters: int) -> dict:
    dev = torch.device("cuda")
    model = build_model(arch, "full", device=dev, seed=0)
    out = {}
    for b in batches:
        images, state, tokens, _ = seeded_inputs(model, b, dev, half_prompt=True)
        graphs, outs = {}, {}
        pool = torch.cuda.graph_pool_handle()
        with torch.inference_mode():
            for name, on in (("main", False), ("gemm", True)):
                set_gemm(on)
                graphs[name], *outs[name] = capture_checked(lambda: model.vlm_stage(images, state, tokens), pool)
            set_gemm(False)
        times = alternating_ms(graphs, iters)
        row = {name: {"p50_ms": statistics.median(times[name]), "p99_ms": pct(times[name], 0.99),
                      "graph_vs_eager_rel": rel(outs[name][1], outs[name][0])} for name in graphs}
        row["gemm"]["rel_err_vs_main"] = rel(outs["gemm"][1], outs["main"][1])
        print(arch, b, json.dumps(row))
        out[b] = row
        graphs.clear()  # the next batch size captures into a fresh pool
    torch.cuda.empty_cache()
    return out


def main():
    models, batches, iters = env_settings("pi0,smolvla,groot_n15,xr0", "1,2,4")
    res = {**result_header(iters), "micro_pi0": micro(iters),
           "models": {m: run_model(m, batches, iters) for m in models}}
    save_result(res, "prefix_attention")
    print(f"\npi0 prefix attention alone, us per call, p50 (rel err vs fp64) ({res['gpu']})")
    for b, r in res["micro_pi0"].items():
        print(f"  b={b}: sdpa {r['sdpa']['us_per_call_p50']:.1f} ({r['sdpa']['rel_err_vs_fp64']:.1e})"
              f"  gemm {r['gemm']['us_per_call_p50']:.1f} ({r['gemm']['rel_err_vs_fp64']:.1e})")
    print(f"\nVLM stage p50 ms, {iters} alternating replays")
    print(f"{'model':10s} {'b':>2s} {'main':>8s} {'gemm':>8s} {'p99 m/g':>14s} {'rel err':>8s} {'g-e':>8s}")
    for m, rows in res["models"].items():
        for b, r in rows.items():
            mm, gg = r["main"], r["gemm"]
            print(f"{m:10s} {b:2d} {mm['p50_ms']:8.3f} {gg['p50_ms']:8.3f} {mm['p99_ms']:6.3f}/{gg['p99_ms']:6.3f}"
                  f" {gg['rel_err_vs_main']:8.1e} {gg['graph_vs_eager_rel']:8.1e}")


if __name__ == "__main__":
    main()
