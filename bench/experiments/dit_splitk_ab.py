"""Experiment: GR00T's action stage with the DiT's residual projections on the split-K GEMM
against the same stage on cuBLAS, side by side in one process.

Each DiT block ends its attention and its feed-forward with ``residual + linear(h)`` with a
bias: on cuBLAS that is a copy of the residual, the GEMM, and a bias add (three launches). With
a workspace, ``layers.linear_residual`` sends it to ``fused.linear_residual_splitk``: one launch
that adds bias and residual in its epilogue (up to 64 rows: batch 1, 49 rows; the first run of this
script also sent batch 2's 98 rows there, which was slower). Over 64 rows the GEMM accumulates into
the residual in place (no copy), then adds the bias. "cublas" here is the stage with no workspace:
GEMM into the residual, bias add (when this was measured, before commit 658932d, also a residual copy).

    OUT=/tmp python bench/experiments/dit_splitk_ab.py
    BATCHES=1 ITERS=100 OUT=/tmp python bench/experiments/dit_splitk_ab.py

Prints a table last and writes ``dit_splitk_ab_<gpu>.json`` (or OUT_NAME) under OUT.
"""
from __future__ import annotations

import json
import os
import statistics
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from shared.models import build_model, groot_n15  # noqa: E402

from norm_fold_ab import kernels_in  # noqa: E402  (this folder)
from timing import (alternating_ms, capture_checked, env_settings, pct, result_header, save_result,  # noqa: E402
                    seeded_inputs)


def run(batches: list[int], iters: int) -> dict:
    dev = torch.device("cuda")
    model = build_model("groot_n15", "full", device=dev, seed=0)
    workspace = groot_n15.Workspace
    out = {}
    for b in batches:
        images, state, tokens, noise = seeded_inputs(model, b, dev)
        graphs, outs, counts = {}, {}, {}
        pool = torch.cuda.graph_pool_handle()
        with torch.inference_mode():
            hand = {k: v.clone() for k, v in model.vlm_stage(images, state, tokens).items()}
            for name, ws in (("cublas", lambda dev: None), ("splitk", workspace)):
                groot_n15.Workspace = ws  # the action stage builds its workspace from this name
                graphs[name], *outs[name] = capture_checked(lambda: model.action_stage(hand, noise), pool, warmup=3)
                counts[name] = kernels_in(lambda: model.action_stage(hand, noise))
            groot_n15.Workspace = workspace
        times = alternating_ms(graphs, iters)
        ref = outs["cublas"][1]
        row = {name: {"p50_ms": statistics.median(times[name]), "p99_ms": pct(times[name], 0.99),
                      "kernels": counts[name], "rel_err_vs_cublas": float((outs[name][1] - ref).norm() / ref.norm()),
                      "graph_vs_eager_max_abs": float((outs[name][1] - outs[name][0]).abs().max())}
               for name in graphs}
        print("groot_n15", b, json.dumps(row))
        out[b] = row
        graphs.clear()
    return out


def main():
    _, batches, iters = env_settings("groot_n15", "1,2,4")
    res = {**result_header(iters), "groot_n15": run(batches, iters)}
    save_result(res, "dit_splitk_ab")
    print(f"\nGR00T action stage, p50 ms (p99), {iters} alternating replays ({res['gpu']})")
    for b, r in res["groot_n15"].items():
        c, s = r["cublas"], r["splitk"]
        print(f"  b={b}: cublas {c['p50_ms']:.3f} ({c['p99_ms']:.3f}) {c['kernels']} kernels   "
              f"splitk {s['p50_ms']:.3f} ({s['p99_ms']:.3f}) {s['kernels']} kernels   rel err {s['rel_err_vs_cublas']:.1e}"
              f"   graph-eager {s['graph_vs_eager_max_abs']:.1e}")


if __name__ == "__main__":
    main()
