"""Experiment: tile sweep of the split-KV Triton attention for pi0's action attention.

The call pi0's action expert makes 180 times per stage at batch 1: 51 queries x 8 heads on one
KV head (408 rows), 662 keys (611 prefix + 51 actions, padded prompt keys masked), D = 256.
18 calls with distinct K/V in one CUDA graph; main's ``small_attention`` against every
(BLOCK_M, BLOCK_N, split cap, warps, stages). Each config is checked against float64 SDPA.
Results: docs/RESULTS.md (model zoo, "Tried and not kept"); raw JSON
bench/results/kernel_exp_attn_sweep_h100.json.

    OUT=/tmp python bench/experiments/attention_tiles.py
"""
import itertools
import json
import os
import statistics
import sys

import torch
import triton

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from shared.models import fused  # noqa: E402
from shared.models.layers import attn_bias  # noqa: E402

OUT = os.environ.get("OUT", "/tmp")
dev = torch.device("cuda")
torch.manual_seed(0)
S, NQ, D, LP = 51, 8, 256, 611
L = LP + S
NL = 18
kv = torch.randn(1, NL, 2, 1, L, D, device=dev, dtype=torch.bfloat16)
qs = [torch.randn(1, S, NQ, D, device=dev, dtype=torch.bfloat16) for _ in range(NL)]
valid = torch.ones(1, L, dtype=torch.bool, device=dev)
valid[:, 300:LP] = False  # padded prompt tokens
bias = attn_bias(valid[:, None, :], NQ, torch.bfloat16)
ws = fused.Workspace(dev)


def qh_of(q):
    return q.reshape(1, S * NQ, 1, D).transpose(1, 2)


def launch(qh, k, v, block_m, block_n, ns_cap, warps, stages):
    b, h, m, d = qh.shape
    length = k.shape[2]
    out = torch.empty(b, m, h, d, device=dev, dtype=qh.dtype).transpose(1, 2)
    b_sb = bias.stride(0) if bias.shape[0] > 1 else 0
    b_sm = bias.stride(2) if bias.shape[2] > 1 else 0
    programs = b * h * triton.cdiv(m, block_m)
    n_split = 1
    while n_split * 2 * programs <= 2 * 132 * (ns_cap / 8) and n_split * 2 * block_n <= length and n_split < ns_cap:
        n_split *= 2
    split_len = triton.cdiv(triton.cdiv(length, n_split), block_n) * block_n
    n_split = triton.cdiv(length, split_len)
    part = torch.empty(b * h * n_split * m, d, device=dev, dtype=torch.float32)
    ml = torch.empty(b * h * n_split * m, 2, device=dev, dtype=torch.float32)
    grid = (b * h, triton.cdiv(m, block_m), n_split)
    cnt = ws.counters(grid[0] * grid[1])
    fused._attn_kernel[grid](qh, k, v, bias, out, part, ml, m, length, h, split_len, d ** -0.5,
                             qh.stride(0), qh.stride(1), qh.stride(2), k.stride(0), k.stride(1), k.stride(2),
                             v.stride(0), v.stride(1), v.stride(2), b_sb, b_sm, out.stride(0), out.stride(1),
                             out.stride(2), cnt, HAS_BIAS=True, SPLIT=n_split > 1, D=d, BLOCK_M=block_m,
                             BLOCK_N=block_n, FUSED_COMBINE=n_split > 1, NS=n_split, num_warps=warps,
                             num_stages=stages)
    return out, n_split


def graph_of(fn):
    for _ in range(2):
        fn()
    torch.cuda.synchronize()
    g = torch.cuda.CUDAGraph()
    with torch.cuda.graph(g):
        res = fn()
    return g, res


def time_graph(g, reps=100):
    for _ in range(10):
        g.replay()
    xs = []
    for _ in range(reps):
        e0, e1 = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        e0.record()
        g.replay()
        e1.record()
        xs.append((e0, e1))
    torch.cuda.synchronize()
    return statistics.median(a.elapsed_time(b) for a, b in xs) * 1000 / NL


def main():
    ref = [torch.nn.functional.scaled_dot_product_attention(qh_of(q).double(), kv[:, i, 0].double(),
                                                            kv[:, i, 1].double(), attn_mask=bias.double())
           for i, q in enumerate(qs)]
    res = []
    g_main, outs = graph_of(lambda: [fused.small_attention(qh_of(q), kv[:, i, 0], kv[:, i, 1], bias, ws)
                                     for i, q in enumerate(qs)])
    t_main = time_graph(g_main)
    print(f"main small_attention: {t_main:.2f} us/call", flush=True)
    for bm, bn, ns, w, st in itertools.product((16, 32, 64), (32, 64), (4, 8, 16), (4, 8), (1, 2, 3)):
        if bm == 64 and w == 4 and bn == 64:
            continue
        try:
            meta = {}

            def fn():
                outs = []
                for i, q in enumerate(qs):
                    o, meta["ns"] = launch(qh_of(q), kv[:, i, 0], kv[:, i, 1], bm, bn, ns, w, st)
                    outs.append(o)
                return outs
            g, outs = graph_of(fn)
            t = time_graph(g)
            g.replay()
            torch.cuda.synchronize()
            err = max(((o.double() - r).abs().max() / r.abs().max()).item() for o, r in zip(outs, ref))
            res.append({"block_m": bm, "block_n": bn, "ns_cap": ns, "ns": meta["ns"], "warps": w, "stages": st,
                        "us": round(t, 2), "rel_err": err})
        except Exception as ex:
            res.append({"block_m": bm, "block_n": bn, "ns_cap": ns, "warps": w, "stages": st, "error": repr(ex)[:200]})
    ok = sorted((r for r in res if "us" in r and r["rel_err"] < 1e-2), key=lambda r: r["us"])
    with open(os.path.join(OUT, "attn_sweep.json"), "w") as f:
        json.dump({"gpu": torch.cuda.get_device_name(), "main_us": t_main, "configs": res}, f, indent=1)
    print(f"{'bm':>3s} {'bn':>3s} {'cap':>3s} {'ns':>3s} {'w':>2s} {'st':>2s} {'us':>6s}")
    for r in ok[:15]:
        print(f"{r['block_m']:3d} {r['block_n']:3d} {r['ns_cap']:3d} {r['ns']:3d} {r['warps']:2d} {r['stages']:2d} "
              f"{r['us']:6.2f}")
    print(f"errors: {sum('error' in r for r in res)}, bad: {sum('us' in r and r['rel_err'] >= 1e-2 for r in res)}")


if __name__ == "__main__":
    main()
