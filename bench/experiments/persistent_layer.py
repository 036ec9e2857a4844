"""Experiment: one persistent Triton kernel per action-expert layer-step (pi0's expert).

A layer-step on main is 9 kernels (norm, QKV, split/RoPE, attention, o + residual, norm,
gate/up, activation, down + residual). Here it is one launch of about one program per SM
that walks five phases separated by grid barriers:

  1. QKV GEMM of the raw x with the attention-norm weight folded into the weight columns,
     1/rms applied to the accumulator, RoPE, q / k / v written to their buffers;
  2. split-KV attention, the last program of a row block merging the slices;
  3. o projection, split-K, the last program of a tile adding the residual (x1) and
     writing that tile's per-row sum of squares (for phase 4's norm);
  4. gate/up GEMM of raw x1 with the MLP-norm weight folded in, 1/rms, gated activation;
  5. down projection like 3, its per-row sums of squares feeding the next layer's phase 1.

No operand is modified in registers before its dot (the norms sit in the folded weights and
the epilogue), so every A tile stays in the asynchronous copy pipeline.

The grid barrier needs every program resident at once: the grid is at most one program per
SM. That is true on an idle GPU. Beside a VLM kernel that holds SMs, the programs that are
resident spin until the rest get an SM. This cannot deadlock, because the VLM kernels never
wait on the action stage, but it takes SMs from the VLM.

Result on an H100 (docs/RESULTS.md, model zoo, "A persistent kernel per layer-step,
measured"): pi0's action stage drops from 9.72 to 7.68 ms alone at batch 1. Beside the VLM
on a 64-SM green context, both stages finish at 16.8 ms against main's 13.4, so the kernel
is not on main.

    OUT=/tmp CORUN=1 RUNS=2 ITERS=50 python bench/experiments/persistent_layer.py          # the record
    OUT=/tmp SWEEP=0 RUNS=1 ITERS=30 python bench/experiments/persistent_layer.py          # first revision
    OUT=/tmp SWEEP=1 RUNS=1 ITERS=30 python bench/experiments/persistent_layer.py          # tile sweep
    OUT=/tmp SWEEP=2 CORUN=1 RUNS=1 ITERS=30 python bench/experiments/persistent_layer.py  # tile sweep 2
    OUT=/tmp DISJOINT=1 CORUN=1 RUNS=2 ITERS=30 python bench/experiments/persistent_layer.py  # + own partition

    # TMA loads, the action stage on a small partition of its own beside the VLM (batch 2)
    OUT=/tmp OUT_NAME=kernel_exp_small_partition_h100.json SWEEP=5 SMALL=24,32 SMALL_SET=main,tma_b \
        BATCHES=2 ITERS=30 python bench/experiments/persistent_layer.py

SWEEP defaults to 3. Variants with ``timing`` stamp ``%globaltimer`` at each phase boundary;
RUNS=2 adds batch 2 (BATCHES picks the batches). CORUN_SMS sets the VLM's green context for
CORUN (64). SMALL lists action-partition sizes for ``small_partition_times``, SMALL_SET the
variants of SMALL_VARIANTS it runs there. With ``tma`` the GEMM phases load their A and weight
tiles through TMA tensor descriptors (bench/experiments/weight_streaming.py measured why).
That second result, on an H100: on 24 or 32 SMs of its own the action stage is slower than
main's kernels there. The VLM alone on the other 108 SMs took 14.9 ms at batch 2 (11.0 on the
whole GPU), but that was cuBLAS choosing kernels for 132 SMs. Captured with its GEMMs planned
for its SM count, as main now captures restricted VLM graphs, it stays close to its SM share
(docs/RESULTS.md, "Weight streaming per SM, and the action stage on a partition of its own",
and "cuBLAS told the SM level").
"""
from __future__ import annotations

import json
import os
import statistics
import sys
import time

import torch
import triton
import triton.language as tl

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from shared.models import build_model, fused, layers  # noqa: E402
from shared.models.fused import _combine_rows, _qkv_pairs_store  # noqa: E402

from timing import alternating_ms, pct, replay_ms, route_expert_layers  # noqa: E402  (this folder)

OUT = os.environ.get("OUT", "/tmp")
_ON_GPU = tl.constexpr(os.environ.get("TRITON_INTERPRET", "0") != "1")  # the CPU interpreter has no inline asm


@triton.jit
def _ld_acquire(ptr):
    return tl.inline_asm_elementwise("ld.global.acquire.gpu.b32 $0, [$1];", "=r,l", [ptr], dtype=tl.int32,
                                     is_pure=False, pack=1)


@triton.jit
def _fence_proxy_async():
    # Generic-proxy stores of other programs, ordered before this program's TMA (async-proxy) reads.
    tl.inline_asm_elementwise("fence.proxy.async.global; mov.u32 $0, 0;", "=r", [], dtype=tl.int32,
                              is_pure=False, pack=1)


@triton.jit
def _grid_sync(bar_ptr, target, POLL_LOAD: tl.constexpr, TMA: tl.constexpr = False):
    # Cooperative-groups style: every thread's stores are done (bar.sync), one release
    # arrival per program, spin on an acquire until all programs of this phase arrived.
    tl.debug_barrier()
    tl.atomic_add(bar_ptr, 1, sem="release", scope="gpu")
    if POLL_LOAD:
        cur = _ld_acquire(bar_ptr)
        while cur < target:
            cur = _ld_acquire(bar_ptr)
    else:
        cur = tl.atomic_add(bar_ptr, 0, sem="acquire", scope="gpu")
        while cur < target:
            cur = tl.atomic_add(bar_ptr, 0, sem="acquire", scope="gpu")
    if TMA and _ON_GPU:
        _fence_proxy_async()
    tl.debug_barrier()


@triton.jit
def _stamp(ts_ptr, pid, idx, TIMING: tl.constexpr):
    if TIMING:
        t = tl.inline_asm_elementwise("mov.u64 $0, %globaltimer;", "=l,r", [pid], dtype=tl.int64,
                                      is_pure=False, pack=1)
        tl.store(ts_ptr + pid * 10 + idx, t)


@triton.jit
def _phase_end(ts_ptr, bar_ptr, pid, nprog, k, TIMING: tl.constexpr, POLL_LOAD: tl.constexpr,
               TMA: tl.constexpr = False):
    """The grid barrier after phase ``k`` (1-based), stamped on both sides."""
    _stamp(ts_ptr, pid, 2 * k - 1, TIMING)
    _grid_sync(bar_ptr, k * nprog, POLL_LOAD, TMA)
    _stamp(ts_ptr, pid, 2 * k, TIMING)


@triton.jit
def _inv_rms(ss_ptr, offs_m, m_ok, K, eps, SS_T: tl.constexpr):
    t = tl.arange(0, SS_T)
    ss = tl.load(ss_ptr + offs_m[:, None] * SS_T + t[None, :], mask=m_ok[:, None], other=0.0,
                 cache_modifier=".cg")
    return tl.rsqrt(tl.sum(ss, 1) / K + eps)


@triton.jit
def _qkv_unit(pid_n, x_ptr, ss_ptr, w_ptr, cos_ptr, sin_ptr, q_ptr, k_ptr, v_ptr, M, K, S, eps,
              n_q, n_kv, stride_x, cos_sb, cos_ss, q_sb, q_ss, q_sh, k_sb, k_ss, k_sh, v_sb, v_ss, v_sh,
              SS_T: tl.constexpr, HALF: tl.constexpr, BM: tl.constexpr, BN: tl.constexpr, BK: tl.constexpr,
              ST: tl.constexpr, INTERLEAVE: tl.constexpr, TMA: tl.constexpr = False, x_desc=None, w_desc=None):
    offs_m = tl.arange(0, BM)
    m_ok = offs_m < M
    j = pid_n * BN + tl.arange(0, BN)  # RoPE pair index over all heads
    acc1 = tl.zeros([BM, BN], tl.float32)
    acc2 = tl.zeros([BM, BN], tl.float32)
    for k0 in tl.range(0, K, BK, num_stages=ST):
        if TMA:  # w_desc views the weight as [pairs, 2K]: a pair's two rows side by side
            a = x_desc.load([0, k0])
            w1 = w_desc.load([pid_n * BN, k0])
            w2 = w_desc.load([pid_n * BN, K + k0])
        else:
            offs_k = k0 + tl.arange(0, BK)
            a = tl.load(x_ptr + offs_m[:, None] * stride_x + offs_k[None, :], mask=m_ok[:, None], other=0.0)
            w1 = tl.load(w_ptr + (2 * j)[:, None] * K + offs_k[None, :])
            w2 = tl.load(w_ptr + (2 * j + 1)[:, None] * K + offs_k[None, :])
        acc1 = tl.dot(a, tl.trans(w1), acc1)
        acc2 = tl.dot(a, tl.trans(w2), acc2)
    r = _inv_rms(ss_ptr, offs_m, m_ok, K, eps, SS_T)
    acc1 = acc1 * r[:, None]
    acc2 = acc2 * r[:, None]
    _qkv_pairs_store(acc1, acc2, pid_n, offs_m, m_ok[:, None], S, n_q, n_kv, cos_ptr, sin_ptr, cos_sb, cos_ss,
                    q_ptr, k_ptr, v_ptr, q_sb, q_ss, q_sh, k_sb, k_ss, k_sh, v_sb, v_ss, v_sh,
                    True, HALF, BN, INTERLEAVE)


@triton.jit
def _attn_unit(unit, q_ptr, k_ptr, v_ptr, bias_ptr, o_ptr, part_ptr, ml_ptr, cnt_ptr, M, L, H, split_len, sm_scale,
               q_sb, q_sh, q_sm, k_sb, k_sh, k_sl, v_sb, v_sh, v_sl, b_sb, b_sm, o_sb, o_sh, o_sm, n_mb,
               NS: tl.constexpr, D: tl.constexpr, BLOCK_M: tl.constexpr, BLOCK_N: tl.constexpr, ST: tl.constexpr):
    pid_s = unit % NS
    pid_m = (unit // NS) % n_mb
    pid_bh = unit // (NS * n_mb)
    b = pid_bh // H
    h = pid_bh % H
    offs_m = pid_m * BLOCK_M + tl.arange(0, BLOCK_M)
    offs_d = tl.arange(0, D)
    m_ok = offs_m < M
    q = tl.load(q_ptr + b * q_sb + h * q_sh + offs_m[:, None] * q_sm + offs_d[None, :], mask=m_ok[:, None],
                other=0.0, cache_modifier=".cg")
    m_i = tl.full([BLOCK_M], -float("inf"), tl.float32)
    l_i = tl.zeros([BLOCK_M], tl.float32)
    acc = tl.zeros([BLOCK_M, D], tl.float32)
    lo = pid_s * split_len
    hi = tl.minimum(lo + split_len, L)
    for start in tl.range(lo, hi, BLOCK_N, num_stages=ST):
        offs_n = start + tl.arange(0, BLOCK_N)
        n_ok = offs_n < hi
        k = tl.load(k_ptr + b * k_sb + h * k_sh + offs_n[:, None] * k_sl + offs_d[None, :], mask=n_ok[:, None],
                    other=0.0, cache_modifier=".cg")
        s = tl.dot(q, tl.trans(k)) * sm_scale
        s += tl.load(bias_ptr + b * b_sb + offs_m[:, None] * b_sm + offs_n[None, :],
                     mask=m_ok[:, None] & n_ok[None, :], other=0.0).to(tl.float32)
        s = tl.where(n_ok[None, :], s, -float("inf"))
        m_new = tl.maximum(m_i, tl.max(s, 1))
        p = tl.exp(s - m_new[:, None])
        alpha = tl.exp(m_i - m_new)
        l_i = l_i * alpha + tl.sum(p, 1)
        v = tl.load(v_ptr + b * v_sb + h * v_sh + offs_n[:, None] * v_sl + offs_d[None, :], mask=n_ok[:, None],
                    other=0.0, cache_modifier=".cg")
        acc = acc * alpha[:, None] + tl.dot(p.to(v.dtype), v)
        m_i = m_new
    row = (pid_bh * NS + pid_s) * M + offs_m
    tl.store(part_ptr + row[:, None] * D + offs_d[None, :], acc, mask=m_ok[:, None])
    tl.store(ml_ptr + row * 2, m_i, mask=m_ok)
    tl.store(ml_ptr + row * 2 + 1, l_i, mask=m_ok)
    tl.debug_barrier()
    cnt = cnt_ptr + pid_bh * n_mb + pid_m
    if tl.atomic_add(cnt, 1, sem="acq_rel", scope="gpu") == NS - 1:
        _combine_rows(part_ptr, ml_ptr, o_ptr, pid_bh, b, h, offs_m, m_ok, offs_d, M, o_sb, o_sh, o_sm, NS)
        tl.atomic_xchg(cnt, 0, sem="relaxed", scope="gpu")


@triton.jit
def _res_unit(unit, x_ptr, w_ptr, res_ptr, out_ptr, ss_out_ptr, part_ptr, cnt_ptr, M, N, K, k_chunk,
              stride_x, stride_r, stride_o, SPLIT: tl.constexpr, SS_OUT_T: tl.constexpr,
              BM: tl.constexpr, BN: tl.constexpr, BK: tl.constexpr, ST: tl.constexpr,
              TMA: tl.constexpr = False, x_desc=None, w_desc=None):
    pid_s = unit % SPLIT
    pid_n = unit // SPLIT
    offs_m = tl.arange(0, BM)
    offs_n = pid_n * BN + tl.arange(0, BN)
    m_ok = offs_m < M
    acc = tl.zeros([BM, BN], tl.float32)
    lo = pid_s * k_chunk
    for k0 in tl.range(lo, lo + k_chunk, BK, num_stages=ST):
        if TMA:
            a = x_desc.load([0, k0])
            w = w_desc.load([pid_n * BN, k0])
        else:
            offs_k = k0 + tl.arange(0, BK)
            a = tl.load(x_ptr + offs_m[:, None] * stride_x + offs_k[None, :], mask=m_ok[:, None], other=0.0)
            w = tl.load(w_ptr + offs_n[:, None] * K + offs_k[None, :])
        acc = tl.dot(a, tl.trans(w), acc)
    loc = tl.arange(0, BM)[:, None] * BN + tl.arange(0, BN)[None, :]
    tl.store(part_ptr + (pid_n * SPLIT + pid_s) * BM * BN + loc, acc)
    tl.debug_barrier()
    if tl.atomic_add(cnt_ptr + pid_n, 1, sem="acq_rel", scope="gpu") == SPLIT - 1:
        acc = tl.zeros([BM, BN], tl.float32)
        for sp in tl.static_range(SPLIT):
            acc += tl.load(part_ptr + (pid_n * SPLIT + sp) * BM * BN + loc, cache_modifier=".cg")
        mask = m_ok[:, None]
        acc += tl.load(res_ptr + offs_m[:, None] * stride_r + offs_n[None, :], mask=mask, other=0.0,
                       cache_modifier=".cg").to(tl.float32)
        y = acc.to(out_ptr.dtype.element_ty)
        tl.store(out_ptr + offs_m[:, None] * stride_o + offs_n[None, :], y, mask=mask)
        yf = y.to(tl.float32)
        tl.store(ss_out_ptr + offs_m * SS_OUT_T + pid_n, tl.sum(yf * yf, 1), mask=m_ok)
        tl.atomic_xchg(cnt_ptr + pid_n, 0, sem="relaxed", scope="gpu")


@triton.jit
def _res_phase(pid, nprog, a_ptr, w_ptr, res_ptr, out_ptr, ss_out_ptr, part_ptr, cnt_ptr, M, N, K, k_chunk,
               SPLIT: tl.constexpr, SS_T: tl.constexpr, BM: tl.constexpr, BN: tl.constexpr, BK: tl.constexpr,
               ST: tl.constexpr, TMA: tl.constexpr = False, a_desc=None, w_desc=None):
    """``out = res + a W^T`` over all (N tile, K slice) units; contiguous rows of N / K columns."""
    n_units = (N // BN) * SPLIT
    for u0 in range(0, n_units, nprog):
        u = u0 + pid
        if u < n_units:
            _res_unit(u, a_ptr, w_ptr, res_ptr, out_ptr, ss_out_ptr, part_ptr, cnt_ptr, M, N, K, k_chunk,
                      K, N, N, SPLIT, SS_T, BM, BN, BK, ST, TMA, a_desc, w_desc)


@triton.jit
def _gate_up_unit(pid_n, x_ptr, ss_ptr, w_ptr, h_ptr, M, K, F_, eps, stride_x, stride_h,
                  SS_T: tl.constexpr, GELU: tl.constexpr, BM: tl.constexpr, BN: tl.constexpr, BK: tl.constexpr,
                  ST: tl.constexpr, TMA: tl.constexpr = False, x_desc=None, w_desc=None):
    offs_m = tl.arange(0, BM)
    m_ok = offs_m < M
    j = pid_n * BN + tl.arange(0, BN)
    acc1 = tl.zeros([BM, BN], tl.float32)
    acc2 = tl.zeros([BM, BN], tl.float32)
    for k0 in tl.range(0, K, BK, num_stages=ST):
        if TMA:
            a = x_desc.load([0, k0])
            w1 = w_desc.load([pid_n * BN, k0])
            w2 = w_desc.load([F_ + pid_n * BN, k0])
        else:
            offs_k = k0 + tl.arange(0, BK)
            a = tl.load(x_ptr + offs_m[:, None] * stride_x + offs_k[None, :], mask=m_ok[:, None], other=0.0)
            w1 = tl.load(w_ptr + j[:, None] * K + offs_k[None, :])
            w2 = tl.load(w_ptr + (j + F_)[:, None] * K + offs_k[None, :])
        acc1 = tl.dot(a, tl.trans(w1), acc1)
        acc2 = tl.dot(a, tl.trans(w2), acc2)
    r = _inv_rms(ss_ptr, offs_m, m_ok, K, eps, SS_T)
    g = (acc1 * r[:, None]).to(h_ptr.dtype.element_ty).to(tl.float32)
    u = (acc2 * r[:, None]).to(h_ptr.dtype.element_ty).to(tl.float32)
    if GELU:
        a = g * tl.sigmoid(1.5957691216057308 * (g + 0.044715 * g * g * g))
    else:
        a = g * tl.sigmoid(g)
    tl.store(h_ptr + offs_m[:, None] * stride_h + j[None, :], (a * u).to(h_ptr.dtype.element_ty), mask=m_ok[:, None])


@triton.jit
def _layer_kernel(x_ptr, ss0_ptr, wqkv_ptr, cos_ptr, sin_ptr, q_ptr, k_ptr, v_ptr,
                  ka_ptr, va_ptr, bias_ptr, attn_ptr, apart_ptr, aml_ptr,
                  wo_ptr, x1_ptr, ss1_ptr, gpart_ptr, cnt_ptr, bar_ptr,
                  wgu_ptr, h_ptr, wd_ptr, out_ptr, ss2_ptr,
                  M, S, W, F_, NQD, eps, n_q, n_kv, sm_scale, L, Mq, split_len, n_mb,
                  cos_sb, cos_ss, q_sb, q_ss, q_sh, k_sb, k_ss, k_sh, v_sb, v_ss, v_sh,
                  ka_sb, ka_sh, ka_sl, va_sb, va_sh, va_sl, b_sb, b_sm,
                  o_chunk, d_chunk, nprog, ts_ptr,
                  TIMING: tl.constexpr, POLL_LOAD: tl.constexpr, SS0_T: tl.constexpr, SS_T: tl.constexpr, HALF: tl.constexpr, D: tl.constexpr, NS: tl.constexpr,
                  SPLIT: tl.constexpr, GELU: tl.constexpr, BM: tl.constexpr, BN_QKV: tl.constexpr,
                  BN: tl.constexpr, BK_QKV: tl.constexpr, BK_GU: tl.constexpr, BK_O: tl.constexpr,
                  BK_D: tl.constexpr, ST: tl.constexpr, A_BM: tl.constexpr, A_BN: tl.constexpr, A_ST: tl.constexpr,
                  INTERLEAVE: tl.constexpr, TMA: tl.constexpr = False, x_d=None, wqkv_d=None, attn_d=None,
                  wo_d=None, x1_d=None, wgu_d=None, h_d=None, wd_d=None):
    pid = tl.program_id(0)  # nprog: the grid size (an argument: the interpreter's num_programs is an array)
    _stamp(ts_ptr, pid, 0, TIMING)
    # 1. norm + QKV + RoPE + KV write
    n_units = ((n_q + 2 * n_kv) * HALF) // BN_QKV
    for u0 in range(0, n_units, nprog):
        u = u0 + pid
        if u < n_units:
            _qkv_unit(u, x_ptr, ss0_ptr, wqkv_ptr, cos_ptr, sin_ptr, q_ptr, k_ptr, v_ptr, M, W, S, eps,
                      n_q, n_kv, W, cos_sb, cos_ss, q_sb, q_ss, q_sh, k_sb, k_ss, k_sh, v_sb, v_ss, v_sh,
                      SS0_T, HALF, BM, BN_QKV, BK_QKV, ST, INTERLEAVE, TMA, x_d, wqkv_d)
    _phase_end(ts_ptr, bar_ptr, pid, nprog, 1, TIMING, POLL_LOAD)
    # 2. attention over [prefix ; state ; actions]; q rows fold the query heads of a KV head
    n_bh = (M // S) * n_kv
    for u0 in range(0, n_bh * n_mb * NS, nprog):
        u = u0 + pid
        if u < n_bh * n_mb * NS:
            _attn_unit(u, q_ptr, ka_ptr, va_ptr, bias_ptr, attn_ptr, apart_ptr, aml_ptr, cnt_ptr, Mq, L, n_kv,
                       split_len, sm_scale, S * n_q * D, D, n_kv * D, ka_sb, ka_sh, ka_sl, va_sb, va_sh, va_sl,
                       b_sb, b_sm, S * n_q * D, D, n_kv * D, n_mb, NS, D, A_BM, A_BN, A_ST)
    _phase_end(ts_ptr, bar_ptr, pid, nprog, 2, TIMING, POLL_LOAD, TMA)
    # 3. o projection + residual -> x1 (+ its per-tile sums of squares)
    _res_phase(pid, nprog, attn_ptr, wo_ptr, x_ptr, x1_ptr, ss1_ptr, gpart_ptr, cnt_ptr + 4096, M, W, NQD, o_chunk,
               SPLIT, SS_T, BM, BN, BK_O, ST, TMA, attn_d, wo_d)
    _phase_end(ts_ptr, bar_ptr, pid, nprog, 3, TIMING, POLL_LOAD, TMA)
    # 4. norm + gate/up + activation -> h
    for u0 in range(0, F_ // BN, nprog):
        u = u0 + pid
        if u < F_ // BN:
            _gate_up_unit(u, x1_ptr, ss1_ptr, wgu_ptr, h_ptr, M, W, F_, eps, W, F_, SS_T, GELU, BM, BN, BK_GU, ST,
                          TMA, x1_d, wgu_d)
    _phase_end(ts_ptr, bar_ptr, pid, nprog, 4, TIMING, POLL_LOAD, TMA)
    # 5. down projection + residual -> out (+ sums of squares for the next layer's norm)
    _res_phase(pid, nprog, h_ptr, wd_ptr, x1_ptr, out_ptr, ss2_ptr, gpart_ptr, cnt_ptr + 4096, M, W, F_, d_chunk,
               SPLIT, SS_T, BM, BN, BK_D, ST, TMA, h_d, wd_d)
    _stamp(ts_ptr, pid, 9, TIMING)


CFG = {"timing": False, "poll_load": False, "grid": None, "bn_qkv": 16, "bn": 32, "split": 4, "warps": 4,
       "bk_qkv": 64, "bk_gu": 64, "bk_o": 64, "bk_d": 64, "stages": 3, "a_bm": 16, "a_bn": None, "a_stages": 3,
       "attn_one_wave": False, "interleave": False, "tma": False}


class PersistentState:
    """Per-stage-call scratch: zeroed counters and one barrier slot per launch."""

    def __init__(self, device):
        self.cnt = torch.zeros(8192, dtype=torch.int32, device=device)
        self.bar = torch.zeros(4096, dtype=torch.int32, device=device)
        self.next_bar = 0
        self.ts = torch.zeros(256, 132, 10, dtype=torch.int64, device=device) if CFG["timing"] else self.cnt


def _folded(layer):
    """QKV and gate/up weights with the norm weights folded in: main's copies (``layers.folded_weight``)."""
    return (layers.folded_weight(layer.attn.qkv, layer.attn_norm),
            layers.folded_weight(layer.mlp.gate_up, layer.mlp_norm))


def layer_persistent(layer, x, k_out, v_out, rope, bias, k_all, v_all, st: PersistentState):
    b, s, w = x.shape
    m = b * s
    at = layer.attn
    n_q, n_kv, d = at.n_heads, at.n_kv_heads, at.head_dim
    f = layer.mlp.down.weight.shape[1]
    assert w % CFG["bn"] == 0 and (w // CFG["bn"]) & (w // CFG["bn"] - 1) == 0 and bias is not None
    assert m <= 128 and at.qkv.bias is None and at.q_norm is None and layer.mlp.down.bias is None
    wqkv, wgu = _folded(layer)
    dev = x.device
    x2 = x.reshape(m, w)
    ss0 = getattr(x, "_ss", None)  # set on the output of the previous persistent layer
    if ss0 is None:
        ss0 = x2.float().square().sum(-1, keepdim=True)
    ss0_t = ss0.shape[1]
    cos, sin = rope
    cos_sb = cos.stride(0) if cos.shape[0] > 1 else 0
    q = torch.empty(b, s, n_q, d, device=dev, dtype=x.dtype)
    attn = torch.empty(m, n_q * d, device=dev, dtype=x.dtype)
    x1 = torch.empty(m, w, device=dev, dtype=x.dtype)
    h = torch.empty(m, f, device=dev, dtype=x.dtype)
    out = torch.empty(m, w, device=dev, dtype=x.dtype)
    bn, split = CFG["bn"], CFG["split"]
    ss1 = torch.empty(m, w // bn, device=dev, dtype=torch.float32)
    ss2 = torch.empty(m, w // bn, device=dev, dtype=torch.float32)
    bm = max(16, triton.next_power_of_2(m))
    gpart = torch.empty((w // bn) * split * bm * bn, device=dev, dtype=torch.float32)
    # attention geometry as small_attention picks it
    mq = s * (n_q // n_kv)
    length = k_all.shape[2]
    a_bm, a_bn = CFG["a_bm"], CFG["a_bn"] or (64 if d <= 128 else 32)
    n_mb = triton.cdiv(mq, a_bm)
    sm = fused._sm_count(dev)
    grid = CFG["grid"] or sm
    programs = b * n_kv * n_mb
    ns = 1
    if CFG["attn_one_wave"]:  # as many key slices as keep every unit in one round of the grid
        ns = max(1, min(grid // programs, triton.cdiv(length, a_bn), 16))
    else:
        while ns * 2 * programs <= 2 * sm and ns * 2 * a_bn <= length and ns < 8:
            ns *= 2
    split_len = triton.cdiv(triton.cdiv(length, ns), a_bn) * a_bn
    ns = triton.cdiv(length, split_len)
    apart = torch.empty(b * n_kv * ns * mq, d, device=dev, dtype=torch.float32)
    aml = torch.empty(b * n_kv * ns * mq, 2, device=dev, dtype=torch.float32)
    b_sb = bias.stride(0) if bias.shape[0] > 1 else 0
    b_sm = bias.stride(2) if bias.shape[2] > 1 else 0
    bar = st.bar[st.next_bar:]
    st.next_bar += 1
    descs = {}
    if CFG["tma"]:  # TMA descriptors: the A tiles' rows past m read as zeros
        from triton.tools.tensor_descriptor import TensorDescriptor as TD
        bq, bk_q, bk_gu, bk_o, bk_d = CFG["bn_qkv"], CFG["bk_qkv"], CFG["bk_gu"], CFG["bk_o"], CFG["bk_d"]
        wo, wd = at.o.weight, layer.mlp.down.weight
        descs = dict(TMA=True, x_d=TD(x2, [m, w], [w, 1], [bm, bk_q]),
                     wqkv_d=TD.from_tensor(wqkv.view(wqkv.shape[0] // 2, 2 * w), [bq, bk_q]),
                     attn_d=TD(attn, [m, n_q * d], [n_q * d, 1], [bm, bk_o]), wo_d=TD.from_tensor(wo, [bn, bk_o]),
                     x1_d=TD(x1, [m, w], [w, 1], [bm, bk_gu]), wgu_d=TD.from_tensor(wgu, [bn, bk_gu]),
                     h_d=TD(h, [m, f], [f, 1], [bm, bk_d]), wd_d=TD.from_tensor(wd, [bn, bk_d]))
    _layer_kernel[(grid,)](
        x2, ss0, wqkv, cos, sin, q, k_out, v_out, k_all, v_all, bias, attn, apart, aml,
        at.o.weight, x1, ss1, gpart, st.cnt, bar, wgu, h, layer.mlp.down.weight, out, ss2,
        m, s, w, f, n_q * d, layer.attn_norm.eps, n_q, n_kv, d ** -0.5, length, mq, split_len, n_mb,
        cos_sb, cos.stride(1), q.stride(0), q.stride(1), q.stride(2),
        k_out.stride(0), k_out.stride(2), k_out.stride(1), v_out.stride(0), v_out.stride(2), v_out.stride(1),
        k_all.stride(0), k_all.stride(1), k_all.stride(2), v_all.stride(0), v_all.stride(1), v_all.stride(2),
        b_sb, b_sm, triton.cdiv(n_q * d, split), triton.cdiv(f, split), grid, st.ts[st.next_bar - 1] if CFG["timing"] else st.ts,
        TIMING=CFG["timing"], POLL_LOAD=CFG["poll_load"],
        SS0_T=ss0_t, SS_T=w // bn, HALF=d // 2, D=d, NS=ns, SPLIT=split, GELU=layer.mlp.act == "gelu_tanh", BM=bm,
        BN_QKV=CFG["bn_qkv"], BN=bn, BK_QKV=CFG["bk_qkv"], BK_GU=CFG["bk_gu"], BK_O=CFG["bk_o"], BK_D=CFG["bk_d"],
        ST=CFG["stages"], A_BM=a_bm, A_BN=a_bn, A_ST=CFG["a_stages"], INTERLEAVE=CFG["interleave"], num_warps=CFG["warps"],
        **descs)
    y = out.view(b, s, w)
    y._ss = ss2
    return y


MODE = {"persistent": False, "state": None}
route_expert_layers(MODE, "persistent", PersistentState, layer_persistent)


VARIANTS = {"main": None}  # name -> CFG overrides (None: main's kernels); main() adds a sweep's
PHASES = ("qkv", "attention", "o", "gate_up", "down")


# the record's configuration: the best of sweeps 1 and 2
RECORD = {"attn_one_wave": True, "timing": True, "bk_qkv": 128, "bk_gu": 128, "bk_o": 128, "bk_d": 128,
          "stages": 4, "warps": 8, "interleave": True, "a_bn": 64, "a_stages": 2}

# TMA tensor-descriptor loads for every GEMM phase, with tiles sized for a grid of ~32
# programs: 128-column weight tiles give 32 units in gate/up, o and down (split-K 4)
TMA_A = {"attn_one_wave": True, "interleave": True, "a_bn": 64, "a_stages": 2, "tma": True, "bn": 128, "split": 4,
         "bn_qkv": 64, "bk_qkv": 64, "bk_gu": 64, "bk_o": 64, "bk_d": 64, "stages": 4, "warps": 4}
SMALL_VARIANTS = {"main": None, "ptr_record": dict(RECORD, timing=False), "ptr_a": dict(TMA_A, tma=False),
                  "tma_a": TMA_A, "tma_b": dict(TMA_A, warps=8),
                  "tma_c": dict(TMA_A, bn=64, split=2, bk_qkv=128, bk_gu=128, bk_o=128, bk_d=128, stages=3)}


def phase_profile(ts: torch.Tensor, launches: int, grid: int) -> dict:
    """Per phase: us from the phase start to the last program's end of work, and the barrier
    after it (last arrival to the median program's exit), averaged over the launches."""
    t = ts[:launches, :grid].double()
    out = {}
    for i, name in enumerate(PHASES):
        start = t[:, :, 2 * i].median(1).values
        work_end = t[:, :, 2 * i + 1].max(1).values
        out[name + "_us"] = float((work_end - start).mean() / 1e3)
        if i < 4:
            out[name + "_barrier_us"] = float((t[:, :, 2 * i + 2].median(1).values - work_end).mean() / 1e3)
    out["launch_us"] = float((t[:, :, 9].max(1).values - t[:, :, 0].min(1).values).mean() / 1e3)
    return out


def _pair_times(gv, vlm_stream, gr, act_stream, iters) -> dict:
    """p50 ms of the VLM graph on ``vlm_stream`` and the action graph on ``act_stream`` after a common start."""
    a_ms, pair_ms, vlm_ms = [], [], []
    for i in range(iters + 5):
        start = torch.cuda.Event(enable_timing=True)
        ea, ev = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        vlm_stream.wait_event(start)
        act_stream.wait_event(start)
        with torch.cuda.stream(vlm_stream):
            gv.replay()
            ev.record(vlm_stream)
        with torch.cuda.stream(act_stream):
            gr.replay()
            ea.record(act_stream)
        torch.cuda.current_stream().wait_stream(vlm_stream)
        torch.cuda.current_stream().wait_stream(act_stream)
        torch.cuda.synchronize()
        if i >= 5:
            a_ms.append(start.elapsed_time(ea))
            vlm_ms.append(start.elapsed_time(ev))
            pair_ms.append(max(a_ms[-1], vlm_ms[-1]))
    return {"action_p50_ms": statistics.median(a_ms), "vlm_p50_ms": statistics.median(vlm_ms),
            "pair_p50_ms": statistics.median(pair_ms)}


def _capture(fn, stream, pool=None):
    """Warm ``fn`` up on ``stream`` and capture it there (a graph keeps its stream's SM limit)."""
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):
        for _ in range(2):
            fn()
    torch.cuda.current_stream().wait_stream(stream)
    g = torch.cuda.CUDAGraph()
    with torch.cuda.graph(g, pool=pool, stream=stream):
        fn()
    return g


def disjoint_times(model, images, state, tokens, hand, noise, iters, vlm_sms=64) -> dict:
    """The disjoint arrangement: the VLM on ``vlm_sms`` SMs and the action stage on the other
    SMs, each a green context of its own. Main's kernels against the persistent kernel with
    one program per SM of the action partition (a larger grid could not be resident there)."""
    from services.executor.sm import split_disjoint
    part = split_disjoint(torch.device("cuda", 0), vlm_sms)
    gv = _capture(lambda: model.vlm_stage(images, state, tokens), part.vlm_stream)
    base = dict(CFG)
    res = {"vlm_sms": part.vlm_sms, "action_sms": part.action_sms}
    for name, cfg in (("main", None), ("persistent", dict(RECORD, timing=False, grid=part.action_sms))):
        MODE["persistent"] = cfg is not None
        CFG.clear()
        CFG.update(base, **(cfg or {}))
        gr = _capture(lambda: model.action_stage(hand, noise), part.action_stream)
        res[name] = dict(_pair_times(gv, part.vlm_stream, gr, part.action_stream, iters),
                         action_alone_p50_ms=_alone_ms(gr, part.action_stream, iters))
    CFG.clear()
    CFG.update(base)
    MODE["persistent"] = False
    return res


def _alone_ms(graph, stream, iters):
    return statistics.median(replay_ms(graph, stream, iters))


def small_partition_times(model, images, state, tokens, hand, noise, iters, action_sms_list, variants) -> dict:
    """The action stage on a small partition of its own, the VLM on the rest of the GPU.

    The action group is split off first so that it gets exactly ``n`` SMs (a multiple of 8)
    and the VLM the remainder. Each variant runs with one program per action SM. Reported per
    partition: the VLM alone on the whole GPU and on its partition, each variant's action
    stage alone on its partition, both stages side by side (a lockstep of this partition),
    and the variant's output against main's on the whole GPU."""
    from services.executor.sm import split_disjoint
    dev = torch.device("cuda", 0)
    plain = torch.cuda.Stream()
    base = dict(CFG)
    MODE["persistent"] = False
    ref = model.action_stage(hand, noise).float()
    g_full = _capture(lambda: model.vlm_stage(images, state, tokens), plain)
    res = {"vlm_alone_full_gpu_p50_ms": _alone_ms(g_full, plain, iters), "partitions": []}
    print(json.dumps({"vlm_alone_full_gpu_p50_ms": res["vlm_alone_full_gpu_p50_ms"]}), flush=True)
    for n in action_sms_list:
        part = split_disjoint(dev, n)  # first group: the action stage's n SMs
        act_stream, vlm_stream = part.vlm_stream, part.action_stream
        gv = _capture(lambda: model.vlm_stage(images, state, tokens), vlm_stream)
        row = {"action_sms": part.vlm_sms, "vlm_sms": part.action_sms,
               "vlm_alone_on_partition_p50_ms": _alone_ms(gv, vlm_stream, iters), "variants": {}}
        for name, cfg in variants.items():
            MODE["persistent"] = cfg is not None
            CFG.clear()
            CFG.update(base, **(dict(cfg, grid=part.vlm_sms) if cfg is not None else {}))
            try:
                out_box = []
                gr = _capture(lambda: out_box.append(model.action_stage(hand, noise)), act_stream)
                gr.replay()
                torch.cuda.synchronize()
                out = out_box[-1].float()
                row["variants"][name] = dict(_pair_times(gv, vlm_stream, gr, act_stream, iters),
                                             action_alone_p50_ms=_alone_ms(gr, act_stream, iters),
                                             rel_err_vs_main=float((out - ref).norm() / ref.norm()))
            except Exception as exc:  # a configuration that does not fit is a result too
                row["variants"][name] = {"error": repr(exc)[:500]}
            print(json.dumps({"partition": n, "vlm_alone_on_partition_p50_ms": row["vlm_alone_on_partition_p50_ms"],
                              name: row["variants"][name]}), flush=True)
        res["partitions"].append(row)
        del gv
    CFG.clear()
    CFG.update(base)
    MODE["persistent"] = False
    return res


def corun_times(model, images, state, tokens, graphs, iters, level=64):
    """The action graph beside the VLM graph restricted to ``level`` SMs (a green context, as
    the lockstep engine runs them): action end and pair end after a common start, p50 ms."""
    from torch.cuda.green_contexts import GreenContext
    ctx = GreenContext.create(num_sms=level, device_id=0)
    green = ctx.Stream()
    gv = _capture(lambda: model.vlm_stage(images, state, tokens), green)
    act = torch.cuda.Stream()
    return {n: dict(_pair_times(gv, green, gr, act, iters), level=level) for n, (gr, _) in graphs.items()}


def run(arch, batch, iters):
    dev = torch.device("cuda")
    model = build_model(arch, "full", device=dev, seed=0)
    with torch.no_grad():  # random norm weights so the folding is really exercised
        g = torch.Generator(device="cpu").manual_seed(7)
        for mod in model.modules():
            if isinstance(mod, layers.RMSNorm):
                mod.weight.copy_((1 + 0.3 * torch.randn(mod.weight.shape, generator=g)).to(mod.weight.dtype))
    gen = torch.Generator().manual_seed(1234 + batch)
    images, state, tokens = model.example_inputs(batch, device=dev, generator=gen)
    tokens[:, model.io.prompt_len // 2:] = 0
    noise = model.noise(batch, device=dev, generator=gen).to(torch.bfloat16)
    with torch.inference_mode():
        hand = model.vlm_stage(images, state, tokens)
        hand = {k: v.clone() for k, v in hand.items()}
        outs, graphs = {}, {}
        pool = torch.cuda.graph_pool_handle()
        base = dict(CFG)
        profiles = {}
        for name, cfg in VARIANTS.items():
            MODE["persistent"] = cfg is not None
            CFG.clear()
            CFG.update(base, **(cfg or {}))
            t0 = time.perf_counter()
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                for _ in range(2):
                    eager = model.action_stage(hand, noise)
            torch.cuda.current_stream().wait_stream(side)
            torch.cuda.synchronize()
            compile_s = time.perf_counter() - t0
            gr = torch.cuda.CUDAGraph()
            with torch.cuda.graph(gr, pool=pool):
                out = model.action_stage(hand, noise)
            gr.replay()
            torch.cuda.synchronize()
            outs[name] = (eager.float().clone(), out.float().clone(), compile_s)
            graphs[name] = (gr, out)
            if cfg is not None and CFG["timing"]:
                profiles[name] = phase_profile(MODE["state"].ts, MODE["state"].next_bar,
                                               CFG["grid"] or fused._sm_count(dev))
        CFG.clear()
        CFG.update(base)
        times = alternating_ms({n: gr for n, (gr, _) in graphs.items()}, iters)
        corun = (corun_times(model, images, state, tokens, graphs, iters, int(os.environ.get("CORUN_SMS", "64")))
                 if os.environ.get("CORUN") else {})
        small = None
        if os.environ.get("SMALL"):
            chosen = os.environ.get("SMALL_SET", ",".join(SMALL_VARIANTS)).split(",")
            small = small_partition_times(model, images, state, tokens, hand, noise, iters,
                                          [int(v) for v in os.environ["SMALL"].split(",")],
                                          {n: SMALL_VARIANTS[n] for n in chosen})
        disjoint = (disjoint_times(model, images, state, tokens, hand, noise, iters)
                    if os.environ.get("DISJOINT") else None)
        main_out = outs["main"][1]
        res = {"arch": arch, "batch": batch}
        for n in graphs:
            eager, graphed, cs = outs[n]
            res[n] = {"p50_ms": statistics.median(times[n]), "p99_ms": pct(times[n], 0.99),
                      "rel_err_vs_main": float((graphed - main_out).norm() / main_out.norm()),
                      "graph_vs_eager_max_abs": float((graphed - eager).abs().max()),
                      "finite": bool(torch.isfinite(graphed).all()), "warmup_s": cs}
            if n in profiles:
                res[n]["phases"] = profiles[n]
            if n in corun:
                res[n]["corun"] = corun[n]
    MODE["persistent"] = False
    if disjoint is not None:
        res["disjoint"] = disjoint
    if small is not None:
        res["small_partition"] = small
    return res


def main():
    torch.manual_seed(0)
    iters = int(os.environ.get("ITERS", "50"))
    results = {"gpu": torch.cuda.get_device_name(0), "date": time.strftime("%Y-%m-%d"), "commit":
               os.environ.get("ROBION_COMMIT", ""), "cfg": dict(CFG), "runs": []}
    sweep = os.environ.get("SWEEP", "3")
    one = {"attn_one_wave": True, "timing": True}
    best = dict(one, bk_qkv=128, bk_gu=128, bk_o=128, bk_d=128, stages=4, warps=8)
    rec = RECORD
    VARIANTS.update({
        # the first revision: main's attention split, BK 64; spin on an atomic or a plain load
        "0": {"persistent": {}, "poll_load": {"poll_load": True},
              "poll_load+timing": {"poll_load": True, "timing": True}, "atomic+timing": {"timing": True}},
        "1": {"bk64": dict(one),
              "bk128": dict(one, bk_qkv=128, bk_gu=128, bk_o=128, bk_d=128, stages=4),
              "bk256": dict(one, bk_qkv=256, bk_gu=256, bk_o=256, bk_d=256, stages=3),
              "bk256_a32": dict(one, bk_qkv=256, bk_gu=256, bk_o=256, bk_d=256, stages=3, a_bm=32, a_bn=64),
              "bk128_w8": best},
        "2": {"best": dict(best, timing=False), "best_t": best,
              "interleave": dict(best, interleave=True),
              "a_bn64": rec,
              "st6": dict(best, interleave=True, stages=6),
              "grid64": dict(best, interleave=True, grid=64)},
        # the record: the best of sweeps 1 and 2, untimed, with per-phase stamps, and on 64 programs
        "3": {"persistent": dict(rec, timing=False), "persistent_phases": rec,
              "persistent_grid64": dict(rec, timing=False, grid=64)},
        # TMA loads; alone on the whole GPU and on 32 programs, with per-phase stamps
        "4": {"persistent": dict(rec, timing=False), "tma_a": TMA_A,
              "ptr_a_grid32": dict(TMA_A, tma=False, grid=32, timing=True),
              "tma_a_grid32": dict(TMA_A, grid=32, timing=True)},
        # the 8-warp TMA tiles on 32 programs, with per-phase stamps
        "5": {"tma_b_grid32": dict(TMA_A, warps=8, grid=32, timing=True)},
    }[sweep])
    batches = [int(v) for v in os.environ.get("BATCHES", "1,2").split(",")][:int(os.environ.get("RUNS", "2"))]
    for arch, batch in [("pi0", b) for b in batches]:
        try:
            results["runs"].append(run(arch, batch, iters))
        except Exception as exc:  # keep the other runs' numbers
            results["runs"].append({"arch": arch, "batch": batch, "error": repr(exc)[:2000]})
        print(json.dumps(results["runs"][-1]), flush=True)
    with open(os.path.join(OUT, os.environ.get("OUT_NAME", "kernel_exp_persistent_layer.json")), "w") as fh:
        json.dump(results, fh, indent=1)
    print(f"\n{results['gpu']} action stage p50 ms (rel err vs main)")
    for r in results["runs"]:
        if "error" in r:
            print(r["arch"], r["batch"], "ERROR", r["error"][:300])
        else:
            print(f"{r['arch']:8s} b{r['batch']}  " + "  ".join(
                f"{n} {r[n]['p50_ms']:.2f} ({r[n]['rel_err_vs_main']:.1e})" for n in VARIANTS))
            for n in VARIANTS:
                if "phases" in r[n]:
                    print("   ", n, " ".join(f"{k}={v:.1f}" for k, v in r[n]["phases"].items()))


if __name__ == "__main__":
    main()
