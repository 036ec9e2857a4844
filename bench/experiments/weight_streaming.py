"""Experiment: how fast can one SM stream GEMM weights for the action stage's 51-row GEMMs?

The persistent-kernel experiment (persistent_layer.py) found each SM moving only about
20 GB/s, with the 51-row A tile re-read from L2 for every weight tile. An action stage that
keeps its solo speed on a small SM partition, beside the VLM, needs several times that.
This measures the per-SM rate directly, on green contexts of 16 to 132 SMs, for the
layer-step's widest GEMM (gate/up, 1024 -> 8192, 16.8 MB of weights) and for QKV
(1024 -> 2560):

  ptr   - the persistent kernel's way: pointer loads into Triton's async-copy pipeline;
  tma   - the same loop with TMA tensor-descriptor loads (the copy engine fills shared
          memory, no registers or address arithmetic per element);
  read  - TMA loads of the weights summed without a dot: the most a program can stream.

Each kernel is persistent (one program per SM of the partition unless GRID_X says more),
walks its weight tiles in one flattened (tile, k) loop so the pipeline never drains between
tiles, and reads a different copy of the weights on every call (8 copies, 134 MB, beyond L2).
Timed as a CUDA graph of 8 calls on the partition's stream, p50 over REPS replays.

    OUT=/tmp python bench/experiments/weight_streaming.py

Result on an H100 (docs/RESULTS.md, "Weight streaming per SM, and the action stage on a
partition of its own"): TMA loads move 1.2-1.45x more bytes per SM than pointer loads on 16 or
32 SMs (gate/up: 57 against 39 GB/s of weights per SM on 16). No launch of a 16.8 MB GEMM
finishes in under about 11 us (1.5 TB/s) at any SM count. With 16 and 32 SMs, the times fit a
fixed cost of about 8 us per launch plus about 100 GB/s per SM.
"""
from __future__ import annotations

import json
import os
import statistics

import torch
import triton
import triton.language as tl
from triton.tools.tensor_descriptor import TensorDescriptor

from timing import replay_ms  # noqa: E402  (this folder)

OUT = os.environ.get("OUT", "/tmp")
REPS = int(os.environ.get("REPS", "30"))
COPIES = 8
M = 51  # pi0's action expert at batch 1: 50 action tokens + 1 state token


@triton.jit
def _stream(a, w, y_ptr, M, N, K, n_tiles,
            BM: tl.constexpr, BN: tl.constexpr, BK: tl.constexpr, STAGES: tl.constexpr, TMA: tl.constexpr):
    """Y = A W^T with ``a`` and ``w`` pointers, or TMA descriptors when TMA."""
    pid = tl.program_id(0)
    grid = tl.num_programs(0)
    kt = K // BK
    mine = (n_tiles - pid + grid - 1) // grid
    rm = tl.arange(0, BM)
    rk = tl.arange(0, BK)
    rn = tl.arange(0, BN)
    acc = tl.zeros((BM, BN), tl.float32)
    for it in tl.range(0, mine * kt, num_stages=STAGES):
        tile = pid + (it // kt) * grid
        k0 = (it % kt) * BK
        if TMA:
            a_t = a.load([0, k0])
            w_t = w.load([tile * BN, k0])
        else:
            a_t = tl.load(a + rm[:, None] * K + k0 + rk[None, :], mask=rm[:, None] < M, other=0.0)
            w_t = tl.load(w + (tile * BN + rn)[:, None] * K + k0 + rk[None, :])
        acc = tl.dot(a_t, tl.trans(w_t), acc)
        if it % kt == kt - 1:
            tl.store(y_ptr + rm[:, None] * N + tile * BN + rn[None, :], acc.to(tl.bfloat16), mask=rm[:, None] < M)
            acc = tl.zeros((BM, BN), tl.float32)


@triton.jit
def _read_tma(w_desc, y_ptr, K, n_tiles, BN: tl.constexpr, BK: tl.constexpr, STAGES: tl.constexpr):
    pid = tl.program_id(0)
    grid = tl.num_programs(0)
    kt = K // BK
    mine = (n_tiles - pid + grid - 1) // grid
    acc = tl.zeros((BN, BK), tl.float32)
    for it in tl.range(0, mine * kt, num_stages=STAGES):
        tile = pid + (it // kt) * grid
        acc += w_desc.load([tile * BN, (it % kt) * BK]).to(tl.float32)
    tl.store(y_ptr + pid, tl.sum(tl.sum(acc, 1), 0))


def _launcher(kind, a, w, y, cfg, grid):
    n, k = w.shape
    bn, bk, st, warps = cfg["BN"], cfg["BK"], cfg["STAGES"], cfg["warps"]
    tiles = n // bn
    if kind == "ptr":
        return lambda: _stream[(grid,)](a, w, y, M, n, k, tiles, BM=64, BN=bn, BK=bk, STAGES=st, TMA=False,
                                        num_warps=warps)
    wd = TensorDescriptor.from_tensor(w, [bn, bk])
    if kind == "tma":
        ad = TensorDescriptor(a, [M, k], [k, 1], [64, bk])
        return lambda: _stream[(grid,)](ad, wd, y, M, n, k, tiles, BM=64, BN=bn, BK=bk, STAGES=st, TMA=True,
                                        num_warps=warps)
    return lambda: _read_tma[(grid,)](wd, y, k, tiles, BN=bn, BK=bk, STAGES=st, num_warps=warps)


def measure(kind, cfg, n, k, stream, sms, grid_x=1):
    """p50 microseconds per call and the rates it implies, on ``stream`` (``sms`` SMs)."""
    gen = torch.Generator(device="cuda").manual_seed(0)
    a = torch.randn(M, k, device="cuda", generator=gen).to(torch.bfloat16)
    ws = [(torch.randn(n, k, device="cuda", generator=gen) / k ** 0.5).to(torch.bfloat16) for _ in range(COPIES)]
    ys = [torch.empty(M, n, device="cuda", dtype=torch.bfloat16) if kind != "read" else
          torch.empty(4096, device="cuda", dtype=torch.float32) for _ in range(COPIES)]
    grid = sms * grid_x
    calls = [_launcher(kind, a, w, y, cfg, grid) for w, y in zip(ws, ys)]
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):
        for c in calls:
            c()
    torch.cuda.current_stream().wait_stream(stream)
    torch.cuda.synchronize()
    err = None
    if kind != "read":
        ref = a.float() @ ws[0].float().t()
        err = ((ys[0].float() - ref).abs().max() / ref.abs().max()).item()
    g = torch.cuda.CUDAGraph()
    with torch.cuda.graph(g, stream=stream):
        for c in calls:
            c()
    us = statistics.median(replay_ms(g, stream, REPS, warmup=3)) * 1000 / COPIES
    w_bytes = n * k * 2
    a_bytes = (n // cfg["BN"]) * M * k * 2 if kind != "read" else 0
    return {"us": us, "weight_TBps": w_bytes / us / 1e6, "weight_GBps_per_sm": w_bytes / us / 1e3 / sms,
            "all_GBps_per_sm": (w_bytes + a_bytes) / us / 1e3 / sms, "rel_err": err}


CONFIGS = {
    "ptr": [dict(BN=64, BK=128, STAGES=4, warps=8), dict(BN=128, BK=128, STAGES=3, warps=8),
            dict(BN=128, BK=64, STAGES=6, warps=4)],
    "tma": [dict(BN=64, BK=128, STAGES=4, warps=4), dict(BN=128, BK=64, STAGES=6, warps=4),
            dict(BN=128, BK=128, STAGES=4, warps=8), dict(BN=256, BK=64, STAGES=4, warps=8),
            dict(BN=64, BK=64, STAGES=8, warps=4)],
    "read": [dict(BN=128, BK=64, STAGES=4, warps=4), dict(BN=128, BK=64, STAGES=8, warps=4),
             dict(BN=256, BK=64, STAGES=4, warps=8)],
}
SHAPES = {"gate_up": (8192, 1024), "qkv": (2560, 1024)}


def main():
    from torch.cuda.green_contexts import GreenContext
    torch.backends.cuda.matmul.allow_tf32 = False
    total = torch.cuda.get_device_properties(0).multi_processor_count
    levels = [int(x) for x in os.environ.get("LEVELS", "16,32,64,0").split(",")]
    keep, streams = [], {}
    for lv in levels:
        if lv == 0:
            streams[total] = torch.cuda.Stream()
        else:
            ctx = GreenContext.create(num_sms=lv, device_id=0)
            keep.append(ctx)
            streams[lv] = ctx.Stream()
    rows = []
    for shape, (n, k) in SHAPES.items():
        for kind, cfgs in CONFIGS.items():
            for cfg in cfgs:
                for sms, stream in streams.items():
                    name = f"{kind} BN{cfg['BN']} BK{cfg['BK']} s{cfg['STAGES']} w{cfg['warps']}"
                    try:
                        r = measure(kind, cfg, n, k, stream, sms)
                    except Exception as exc:  # a config the compiler or TMA rejects is a result too
                        r = {"error": f"{type(exc).__name__}: {str(exc)[:200]}"}
                    rows.append(dict(shape=shape, kind=kind, config=name, sms=sms, **r))
                    print(json.dumps(rows[-1]), flush=True)
    meta = {"gpu": torch.cuda.get_device_name(0), "torch": torch.__version__, "triton": triton.__version__,
            "commit": os.environ.get("ROBION_COMMIT", "unknown"), "reps": REPS, "copies": COPIES, "rows_m": M}
    with open(os.path.join(OUT, "kernel_exp_weight_streaming_h100.json"), "w") as f:
        json.dump({"meta": meta, "rows": rows}, f, indent=1)
    print(f"\n{'shape':8} {'kernel':28} " + " ".join(f"{s:>17}" for s in streams))
    print(f"{'':8} {'':28} " + " ".join(f"{'us  GB/s/SM w(all)':>17}" for _ in streams))
    for shape in SHAPES:
        for kind, cfgs in CONFIGS.items():
            for cfg in cfgs:
                name = f"{kind} BN{cfg['BN']} BK{cfg['BK']} s{cfg['STAGES']} w{cfg['warps']}"
                cells = []
                for sms in streams:
                    r = next(x for x in rows if x["shape"] == shape and x["config"] == name and x["sms"] == sms)
                    cells.append("error" if "error" in r else
                                 f"{r['us']:6.1f} {r['weight_GBps_per_sm']:4.0f}({r['all_GBps_per_sm']:3.0f})")
                print(f"{shape:8} {name:28} " + " ".join(f"{c:>17}" for c in cells))


if __name__ == "__main__":
    main()
