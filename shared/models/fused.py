"""Fused element-wise kernels for the hot loops of the zoo.

The action stages run tens of small layers per Euler step, so their latency is set by
how many kernels they launch, not by bytes. Two fusions remove most of the small
kernels that sit between the GEMMs:

- ``split_qkv``: split a fused QKV projection into heads, optionally apply per-head
  RMSNorm (QK-norm) and RoPE to q and k, and write k and v straight into the caller's
  KV buffers (any strides). One kernel instead of about ten.
- ``gated_act``: ``act(gate) * up`` from a fused gate/up projection. One kernel instead
  of two or three.

On CUDA they are Triton kernels; elsewhere (or without Triton) the same maths in plain
PyTorch ops, which is also the reference the GPU tests compare against.

RoPE here rotates *interleaved* pairs (2i, 2i+1) of each head. Checkpoints using the
rotate-half convention (HF Llama/Gemma) need their q/k projection rows permuted on
conversion; the cost of the op is identical.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

try:  # Triton ships with CUDA builds of torch only.
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - CPU wheels
    triton = None

_USE_TRITON = True  # tests flip this to compare against the reference path


def triton_enabled(t: torch.Tensor) -> bool:
    return _USE_TRITON and triton is not None and t.is_cuda


def set_triton(enabled: bool) -> bool:
    """Turn the Triton fast path on or off; returns the previous setting."""
    global _USE_TRITON
    old, _USE_TRITON = _USE_TRITON, enabled
    return old


# --------------------------------------------------------------------------- reference


def rope_ref(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """x [B, S, H, D]; cos/sin [B or 1, S, D/2] fp32."""
    xf = x.float().unflatten(-1, (-1, 2))
    x0, x1 = xf.unbind(-1)
    c, s = cos[:, :, None, :], sin[:, :, None, :]
    return torch.stack((x0 * c - x1 * s, x0 * s + x1 * c), dim=-1).flatten(-2).to(x.dtype)


def _split_qkv_ref(qkv, n_q, n_kv, head_dim, cos, sin, q_norm, k_norm, eps, k_out, v_out, row_scale=None):
    b, s, _ = qkv.shape
    if row_scale is not None:
        qkv = (qkv.float() * row_scale.view(b, s, 1)).to(qkv.dtype)
    q, k, v = qkv.split([n_q * head_dim, n_kv * head_dim, n_kv * head_dim], dim=-1)
    q = q.unflatten(-1, (n_q, head_dim))
    k = k.unflatten(-1, (n_kv, head_dim))
    v = v.unflatten(-1, (n_kv, head_dim))
    if q_norm is not None:
        q = F.rms_norm(q, (head_dim,), q_norm, eps)
        k = F.rms_norm(k, (head_dim,), k_norm, eps)
    if cos is not None:
        q = rope_ref(q, cos, sin)
        k = rope_ref(k, cos, sin)
    if n_kv:
        k_out.copy_(k.transpose(1, 2))
        v_out.copy_(v.transpose(1, 2))
    return q.contiguous()


def _gated_act_ref(x: torch.Tensor, act: str, row_scale: torch.Tensor | None = None) -> torch.Tensor:
    if row_scale is not None:
        x = (x.float() * row_scale.view(*x.shape[:-1], 1)).to(x.dtype)
    gate, up = x.chunk(2, dim=-1)
    gate = F.gelu(gate, approximate="tanh") if act == "gelu_tanh" else F.silu(gate)
    return gate * up


# --------------------------------------------------------------------------- Triton

if triton is not None:

    @triton.jit
    def _row_rstd(ss_ptr, row, n_tiles, rows, inv_width, eps, TILES: tl.constexpr):
        # 1 / rms of one row from the per-column-tile sums of squares a split-K GEMM left
        # (``RowStats``: [n_tiles, rows] fp32).
        t = tl.arange(0, TILES)
        ss = tl.load(ss_ptr + t * rows + row, mask=t < n_tiles, other=0.0)
        return tl.rsqrt(tl.sum(ss, 0) * inv_width + eps)

    @triton.jit
    def _split_qkv_kernel(
        qkv_ptr, cos_ptr, sin_ptr, qn_ptr, kn_ptr, q_ptr, k_ptr, v_ptr,
        S, n_q, n_kv, stride_row, cos_sb, cos_ss,
        q_sb, q_ss, q_sh, k_sb, k_ss, k_sh, v_sb, v_ss, v_sh, eps,
        ss_ptr, n_tiles, rows, inv_width, row_eps,
        HALF: tl.constexpr, BLOCK: tl.constexpr, ROPE: tl.constexpr, QKNORM: tl.constexpr,
        ROWSCALE: tl.constexpr, TILES: tl.constexpr,
    ):
        row = tl.program_id(0)
        head = tl.program_id(1)
        b = row // S
        s = row % S
        i = tl.arange(0, BLOCK)
        m = i < HALF
        src = qkv_ptr + row * stride_row + head * 2 * HALF
        x0 = tl.load(src + 2 * i, mask=m, other=0.0).to(tl.float32)
        x1 = tl.load(src + 2 * i + 1, mask=m, other=0.0).to(tl.float32)
        if ROWSCALE:
            r = _row_rstd(ss_ptr, row, n_tiles, rows, inv_width, row_eps, TILES)
            x0 = x0 * r
            x1 = x1 * r
        if head < n_q + n_kv:
            if QKNORM:
                r = tl.rsqrt((tl.sum(x0 * x0, 0) + tl.sum(x1 * x1, 0)) / (2 * HALF) + eps)
                if head < n_q:
                    w0 = tl.load(qn_ptr + 2 * i, mask=m, other=0.0).to(tl.float32)
                    w1 = tl.load(qn_ptr + 2 * i + 1, mask=m, other=0.0).to(tl.float32)
                else:
                    w0 = tl.load(kn_ptr + 2 * i, mask=m, other=0.0).to(tl.float32)
                    w1 = tl.load(kn_ptr + 2 * i + 1, mask=m, other=0.0).to(tl.float32)
                x0 = x0 * r * w0
                x1 = x1 * r * w1
            if ROPE:
                c = tl.load(cos_ptr + b * cos_sb + s * cos_ss + i, mask=m, other=0.0)
                sn = tl.load(sin_ptr + b * cos_sb + s * cos_ss + i, mask=m, other=0.0)
                y0 = x0 * c - x1 * sn
                y1 = x0 * sn + x1 * c
            else:
                y0 = x0
                y1 = x1
            if head < n_q:
                dst = q_ptr + b * q_sb + s * q_ss + head * q_sh
            else:
                dst = k_ptr + b * k_sb + s * k_ss + (head - n_q) * k_sh
            tl.store(dst + 2 * i, y0.to(dst.dtype.element_ty), mask=m)
            tl.store(dst + 2 * i + 1, y1.to(dst.dtype.element_ty), mask=m)
        else:
            dst = v_ptr + b * v_sb + s * v_ss + (head - n_q - n_kv) * v_sh
            tl.store(dst + 2 * i, x0.to(dst.dtype.element_ty), mask=m)
            tl.store(dst + 2 * i + 1, x1.to(dst.dtype.element_ty), mask=m)

    @triton.jit
    def _resize_table_kernel(src_ptr, out_ptr, G, g, C, scale, BLOCK_C: tl.constexpr):
        # Bilinear resize (align_corners=False) of a channels-last [G, G, C] table to [g, g, C],
        # PyTorch's taps and order of operations in fp32. Its CUDA kernel parallelises over
        # the output pixels only and loops over the channels: 605 us for XR0's 48x48x1024 ->
        # 16x16 position table, on every VLM call.
        p = tl.program_id(0)
        c = tl.program_id(1) * BLOCK_C + tl.arange(0, BLOCK_C)
        cm = c < C
        oy = p // g
        ox = p % g
        sy = tl.maximum(scale * (oy.to(tl.float32) + 0.5) - 0.5, 0.0)
        sx = tl.maximum(scale * (ox.to(tl.float32) + 0.5) - 0.5, 0.0)
        y0 = sy.to(tl.int32)
        x0 = sx.to(tl.int32)
        ly1 = sy - y0.to(tl.float32)
        lx1 = sx - x0.to(tl.float32)
        y1 = y0 + (y0 < G - 1).to(tl.int32)
        x1 = x0 + (x0 < G - 1).to(tl.int32)
        a = tl.load(src_ptr + (y0 * G + x0) * C + c, mask=cm, other=0.0).to(tl.float32)
        b = tl.load(src_ptr + (y0 * G + x1) * C + c, mask=cm, other=0.0).to(tl.float32)
        d = tl.load(src_ptr + (y1 * G + x0) * C + c, mask=cm, other=0.0).to(tl.float32)
        e = tl.load(src_ptr + (y1 * G + x1) * C + c, mask=cm, other=0.0).to(tl.float32)
        val = (1.0 - ly1) * ((1.0 - lx1) * a + lx1 * b) + ly1 * ((1.0 - lx1) * d + lx1 * e)
        tl.store(out_ptr + p * C + c, val.to(out_ptr.dtype.element_ty), mask=cm)

    @triton.jit
    def _gated_act_kernel(x_ptr, out_ptr, n_cols, stride_x, stride_o, ss_ptr, n_tiles, rows, inv_width, row_eps,
                          BLOCK: tl.constexpr, GELU: tl.constexpr, ROWSCALE: tl.constexpr, TILES: tl.constexpr):
        row = tl.program_id(0)
        col = tl.program_id(1) * BLOCK + tl.arange(0, BLOCK)
        m = col < n_cols
        g = tl.load(x_ptr + row * stride_x + col, mask=m, other=0.0).to(tl.float32)
        u = tl.load(x_ptr + row * stride_x + n_cols + col, mask=m, other=0.0).to(tl.float32)
        if ROWSCALE:
            r = _row_rstd(ss_ptr, row, n_tiles, rows, inv_width, row_eps, TILES)
            g = g * r
            u = u * r
        if GELU:
            # 0.5 * (1 + tanh(z)) == sigmoid(2z)
            a = g * tl.sigmoid(1.5957691216057308 * (g + 0.044715 * g * g * g))
        else:
            a = g * tl.sigmoid(g)
        tl.store(out_ptr + row * stride_o + col, (a * u).to(out_ptr.dtype.element_ty), mask=m)


    @triton.jit
    def _combine_rows(part_ptr, ml_ptr, o_ptr, pid_bh, b, h, offs_m, m_ok, offs_d, M, o_sb, o_sh, o_sm,
                      NS: tl.constexpr):
        m_max = tl.full(offs_m.shape, -float("inf"), tl.float32)
        for sp in tl.static_range(NS):
            row = (pid_bh * NS + sp) * M + offs_m
            m_max = tl.maximum(m_max, tl.load(ml_ptr + row * 2, mask=m_ok, other=-float("inf"), cache_modifier=".cg"))
        acc = tl.zeros([offs_m.shape[0], offs_d.shape[0]], tl.float32)
        den = tl.zeros(offs_m.shape, tl.float32)
        for sp in tl.static_range(NS):
            row = (pid_bh * NS + sp) * M + offs_m
            w = tl.exp(tl.load(ml_ptr + row * 2, mask=m_ok, other=-float("inf"), cache_modifier=".cg") - m_max)
            w = tl.where(m_ok, w, 0.0)
            den += w * tl.load(ml_ptr + row * 2 + 1, mask=m_ok, other=0.0, cache_modifier=".cg")
            acc += w[:, None] * tl.load(part_ptr + row[:, None] * offs_d.shape[0] + offs_d[None, :],
                                        mask=m_ok[:, None], other=0.0, cache_modifier=".cg")
        o = acc / tl.where(m_ok, den, 1.0)[:, None]
        tl.store(o_ptr + b * o_sb + h * o_sh + offs_m[:, None] * o_sm + offs_d[None, :],
                 o.to(o_ptr.dtype.element_ty), mask=m_ok[:, None])

    @triton.jit
    def _attn_kernel(q_ptr, k_ptr, v_ptr, bias_ptr, o_ptr, part_ptr, ml_ptr, M, L, H, split_len, sm_scale,
                     q_sb, q_sh, q_sm, k_sb, k_sh, k_sl, v_sb, v_sh, v_sl, b_sb, b_sm, o_sb, o_sh, o_sm,
                     cnt_ptr, HAS_BIAS: tl.constexpr, SPLIT: tl.constexpr, D: tl.constexpr, BLOCK_M: tl.constexpr,
                     BLOCK_N: tl.constexpr, FUSED_COMBINE: tl.constexpr = False, NS: tl.constexpr = 1):
        # One program per (batch x kv head, block of query rows, slice of the keys); online
        # softmax over key blocks. With SPLIT the unnormalised partial results and their
        # (max, sum) go to scratch and _attn_combine merges the slices (flash-decoding).
        pid_bh = tl.program_id(0)
        pid_m = tl.program_id(1)
        pid_s = tl.program_id(2)
        b = pid_bh // H
        h = pid_bh % H
        offs_m = pid_m * BLOCK_M + tl.arange(0, BLOCK_M)
        offs_d = tl.arange(0, D)
        m_ok = offs_m < M
        q = tl.load(q_ptr + b * q_sb + h * q_sh + offs_m[:, None] * q_sm + offs_d[None, :], mask=m_ok[:, None],
                    other=0.0)
        m_i = tl.full([BLOCK_M], -float("inf"), tl.float32)
        l_i = tl.zeros([BLOCK_M], tl.float32)
        acc = tl.zeros([BLOCK_M, D], tl.float32)
        lo = pid_s * split_len
        hi = tl.minimum(lo + split_len, L)
        for start in range(lo, hi, BLOCK_N):
            offs_n = start + tl.arange(0, BLOCK_N)
            n_ok = offs_n < hi
            k = tl.load(k_ptr + b * k_sb + h * k_sh + offs_n[:, None] * k_sl + offs_d[None, :], mask=n_ok[:, None],
                        other=0.0)
            s = tl.dot(q, tl.trans(k)) * sm_scale
            if HAS_BIAS:
                s += tl.load(bias_ptr + b * b_sb + offs_m[:, None] * b_sm + offs_n[None, :],
                             mask=m_ok[:, None] & n_ok[None, :], other=0.0).to(tl.float32)
            s = tl.where(n_ok[None, :], s, -float("inf"))
            m_new = tl.maximum(m_i, tl.max(s, 1))
            p = tl.exp(s - m_new[:, None])
            alpha = tl.exp(m_i - m_new)
            l_i = l_i * alpha + tl.sum(p, 1)
            v = tl.load(v_ptr + b * v_sb + h * v_sh + offs_n[:, None] * v_sl + offs_d[None, :], mask=n_ok[:, None],
                        other=0.0)
            acc = acc * alpha[:, None] + tl.dot(p.to(v.dtype), v)
            m_i = m_new
        if SPLIT:
            row = (pid_bh * tl.num_programs(2) + pid_s) * M + offs_m
            tl.store(part_ptr + row[:, None] * D + offs_d[None, :], acc, mask=m_ok[:, None])
            tl.store(ml_ptr + row * 2, m_i, mask=m_ok)
            tl.store(ml_ptr + row * 2 + 1, l_i, mask=m_ok)
            if FUSED_COMBINE:
                # The last of the NS programs of this (head, row block) to finish merges the
                # slices (no second launch). Partials are read back from L2 in a fixed order,
                # so the result does not depend on which program came last.
                tl.debug_barrier()
                cnt = cnt_ptr + pid_bh * tl.num_programs(1) + pid_m
                if tl.atomic_add(cnt, 1, sem="acq_rel", scope="gpu") == NS - 1:
                    _combine_rows(part_ptr, ml_ptr, o_ptr, pid_bh, b, h, offs_m, m_ok, offs_d, M,
                                  o_sb, o_sh, o_sm, NS)
                    tl.atomic_xchg(cnt, 0, sem="relaxed", scope="gpu")
        else:
            o = acc / l_i[:, None]
            tl.store(o_ptr + b * o_sb + h * o_sh + offs_m[:, None] * o_sm + offs_d[None, :],
                     o.to(o_ptr.dtype.element_ty), mask=m_ok[:, None])

    @triton.jit
    def _attn_combine(part_ptr, ml_ptr, o_ptr, M, H, o_sb, o_sh, o_sm,
                      NS: tl.constexpr, D: tl.constexpr, BLOCK_M: tl.constexpr):
        pid_bh = tl.program_id(0)
        pid_m = tl.program_id(1)
        b = pid_bh // H
        h = pid_bh % H
        offs_m = pid_m * BLOCK_M + tl.arange(0, BLOCK_M)
        offs_d = tl.arange(0, D)
        m_ok = offs_m < M
        m_max = tl.full([BLOCK_M], -float("inf"), tl.float32)
        for sp in range(NS):
            row = (pid_bh * NS + sp) * M + offs_m
            m_max = tl.maximum(m_max, tl.load(ml_ptr + row * 2, mask=m_ok, other=-float("inf")))
        acc = tl.zeros([BLOCK_M, D], tl.float32)
        den = tl.zeros([BLOCK_M], tl.float32)
        for sp in range(NS):
            row = (pid_bh * NS + sp) * M + offs_m
            w = tl.exp(tl.load(ml_ptr + row * 2, mask=m_ok, other=-float("inf")) - m_max)
            w = tl.where(m_ok, w, 0.0)
            den += w * tl.load(ml_ptr + row * 2 + 1, mask=m_ok, other=0.0)
            acc += w[:, None] * tl.load(part_ptr + row[:, None] * D + offs_d[None, :], mask=m_ok[:, None], other=0.0)
        o = acc / tl.where(m_ok, den, 1.0)[:, None]
        tl.store(o_ptr + b * o_sb + h * o_sh + offs_m[:, None] * o_sm + offs_d[None, :],
                 o.to(o_ptr.dtype.element_ty), mask=m_ok[:, None])


    @triton.jit
    def _softmax_rows_kernel(s_ptr, bias_ptr, p_ptr, M, L, n_kv, scale, s_sb, s_sm, b_sb, b_sm, p_sb, p_sm,
                             HAS_BIAS: tl.constexpr, BLOCK_L: tl.constexpr, ROWS: tl.constexpr):
        # Row softmax of fp32 attention scores (scale, additive bias) to bf16 probabilities,
        # for ``gemm_attention``: one read of the scores, one write of the probabilities.
        pid_b = tl.program_id(0)
        offs_r = tl.program_id(1) * ROWS + tl.arange(0, ROWS)
        offs_l = tl.arange(0, BLOCK_L)
        l_ok = offs_l < L
        mask = (offs_r < M)[:, None] & l_ok[None, :]
        s = tl.load(s_ptr + pid_b * s_sb + offs_r[:, None] * s_sm + offs_l[None, :], mask=mask, other=0.0) * scale
        if HAS_BIAS:
            s += tl.load(bias_ptr + (pid_b // n_kv) * b_sb + offs_r[:, None] * b_sm + offs_l[None, :], mask=mask,
                         other=0.0).to(tl.float32)
        s = tl.where(l_ok[None, :], s, -float("inf"))
        p = tl.exp(s - tl.max(s, 1)[:, None])
        p = p / tl.sum(p, 1)[:, None]
        tl.store(p_ptr + pid_b * p_sb + offs_r[:, None] * p_sm + offs_l[None, :], p.to(p_ptr.dtype.element_ty),
                 mask=mask)


# --------------------------------------------------------------------------- API


ATTN_CFG = {"max_rows": 1024, "min_lib_programs": 132, "big_rows": 1 << 30, "big_block_m": 64, "big_block_n": 64,
            "big_warps": 8, "gemm": True, "gemm_max_keys": 2048, "gemm_max_heads": 4}


def attention_fits(q: torch.Tensor, rows: int, head_dim: int, heads: int = 1) -> bool:
    """Whether the Triton attention kernel takes this call: few query rows per KV head (the
    action stages), where library kernels leave most SMs idle (one program per 128 rows).
    ``heads`` = batch x KV heads: with enough of them the library kernels fill the GPU."""
    if not (triton_enabled(q) and head_dim in (64, 128, 256) and q.dtype != torch.float32):
        return False
    lib_programs = heads * -(-rows // 128)
    return rows <= ATTN_CFG["max_rows"] and not (ATTN_CFG["min_lib_programs"]
                                                  and lib_programs >= ATTN_CFG["min_lib_programs"])


def _bias_args(bias: torch.Tensor | None, dummy: torch.Tensor) -> tuple[torch.Tensor, int, int]:
    """(pointer, batch stride, row stride) of an additive ``[B or 1, 1, M or 1, L]`` bias for the
    attention kernels; broadcast dims get stride 0. Without a bias, ``dummy`` fills the pointer."""
    if bias is None:
        return dummy, 0, 0
    return bias, bias.stride(0) if bias.shape[0] > 1 else 0, bias.stride(2) if bias.shape[2] > 1 else 0


def small_attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, bias: torch.Tensor | None,
                    ws: "Workspace | None" = None) -> torch.Tensor:
    """q ``[B, H, M, D]`` (any strides, last dim contiguous), k/v ``[B, H, L, D]``, bias additive
    ``[B or 1, 1, M or 1, L]`` -> out ``[B, M, H, D]`` memory order, returned as ``[B, H, M, D]``.

    With a workspace the split-KV partials are merged inside the same launch (see ``Workspace``)."""
    q, k, v = unit_last(q), unit_last(k), unit_last(v)
    if bias is not None:
        bias = unit_last(bias)
    b, h, m, d = q.shape
    length = k.shape[2]
    out = torch.empty(b, m, h, d, device=q.device, dtype=q.dtype).transpose(1, 2)
    big = m > ATTN_CFG["big_rows"]  # prefill-sized: bigger query blocks
    block_m = ATTN_CFG["big_block_m"] if big else 16
    warps = ATTN_CFG["big_warps"] if big else 4
    has_bias = bias is not None
    bias, b_sb, b_sm = _bias_args(bias, q)
    block_n = (64 if d <= 128 else 32) if not big else ATTN_CFG["big_block_n"]
    # Split the keys so that about one wave of programs covers the GPU: with a single KV
    # head (pi0) there are only ~25 query blocks, and a serial walk over all keys per
    # program is latency-bound.
    programs = b * h * triton.cdiv(m, block_m)
    n_split = 1
    while n_split * 2 * programs <= 2 * _sm_count(q.device) and n_split * 2 * block_n <= length and n_split < 8:
        n_split *= 2
    split_len = triton.cdiv(triton.cdiv(length, n_split), block_n) * block_n
    n_split = triton.cdiv(length, split_len)
    split = n_split > 1
    if split:
        part = torch.empty(b * h * n_split * m, d, device=q.device, dtype=torch.float32)
        ml = torch.empty(b * h * n_split * m, 2, device=q.device, dtype=torch.float32)
    else:
        part = ml = out
    grid = (b * h, triton.cdiv(m, block_m), n_split)
    fused_combine = split and ws is not None
    cnt = ws.counters(grid[0] * grid[1]) if fused_combine else ml
    _attn_kernel[grid](q, k, v, bias, out, part, ml, m, length, h, split_len, d ** -0.5,
                       q.stride(0), q.stride(1), q.stride(2), k.stride(0), k.stride(1), k.stride(2),
                       v.stride(0), v.stride(1), v.stride(2), b_sb, b_sm, out.stride(0), out.stride(1), out.stride(2),
                       cnt, HAS_BIAS=has_bias, SPLIT=split, D=d, BLOCK_M=block_m, BLOCK_N=block_n,
                       FUSED_COMBINE=fused_combine, NS=n_split, num_warps=warps, num_stages=2)
    if split and not fused_combine:
        _attn_combine[(b * h, triton.cdiv(m, block_m))](part, ml, out, m, h, out.stride(0), out.stride(1),
                                                         out.stride(2), NS=n_split, D=d, BLOCK_M=block_m,
                                                         num_warps=4)
    return out


def gemm_attention_fits(q: torch.Tensor, rows: int, length: int, head_dim: int, heads: int) -> bool:
    """Whether ``gemm_attention`` takes this call: many query rows on few KV heads over a short
    key sequence (a VLM prefix with GQA/MQA folded), where flash kernels get few programs."""
    return (ATTN_CFG["gemm"] and triton_enabled(q) and q.dtype != torch.float32 and rows > ATTN_CFG["max_rows"]
            and length <= ATTN_CFG["gemm_max_keys"] and heads <= ATTN_CFG["gemm_max_heads"] and head_dim % 8 == 0)


def gemm_attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """Attention as two cuBLAS GEMMs around a row softmax: q ``[B, H, M, D]``, k/v ``[B, H, L, D]``,
    bias ``[B or 1, 1, M or 1, L]`` -> ``[B, H, M, D]``.

    The scores are kept in fp32 (``out_dtype``), so the softmax sees what a flash kernel sees;
    the probabilities are rounded to bf16 before the second GEMM, as a flash kernel does."""
    b, h, m, d = q.shape
    length = k.shape[2]
    qf, kf, vf = (t.reshape(b * h, t.shape[2], d) for t in (q, k, v))
    scores = torch.bmm(qf, kf.transpose(1, 2), out_dtype=torch.float32)
    padded = -(-length // 8) * 8  # 16-byte rows for cuBLAS
    probs = torch.empty(b * h, m, padded, device=q.device, dtype=q.dtype)[..., :length]
    has_bias = bias is not None
    bias, b_sb, b_sm = _bias_args(unit_last(bias) if has_bias else None, scores)
    block_l = triton.next_power_of_2(length)
    rows = max(1, min(16, 4096 // block_l))
    _softmax_rows_kernel[(b * h, triton.cdiv(m, rows))](
        scores, bias, probs, m, length, h, d ** -0.5, scores.stride(0), scores.stride(1), b_sb, b_sm,
        probs.stride(0), probs.stride(1), HAS_BIAS=has_bias, BLOCK_L=block_l, ROWS=rows, num_warps=4)
    return torch.bmm(probs, vf).view(b, h, m, d)


_SM_COUNT: dict[int, int] = {}


def _sm_count(device: torch.device) -> int:
    idx = device.index if device.index is not None else torch.cuda.current_device()
    if idx not in _SM_COUNT:
        _SM_COUNT[idx] = torch.cuda.get_device_properties(idx).multi_processor_count
    return _SM_COUNT[idx]



def split_qkv(qkv: torch.Tensor, n_q: int, n_kv: int, head_dim: int,
              k_out: torch.Tensor | None, v_out: torch.Tensor | None,
              cos: torch.Tensor | None = None, sin: torch.Tensor | None = None,
              q_norm: torch.Tensor | None = None, k_norm: torch.Tensor | None = None,
              eps: float = 1e-6, row_stats: RowStats | None = None, row_eps: float = 1e-6) -> torch.Tensor:
    """Split ``qkv [B, S, (n_q + 2 n_kv) * head_dim]`` into heads.

    Returns q as a new ``[B, S, n_q, head_dim]`` tensor; k and v are written into
    ``k_out`` / ``v_out`` (``[B, n_kv, S, head_dim]`` views, e.g. a slice of a KV cache).
    ``cos``/``sin`` are ``[B or 1, S, head_dim / 2]`` fp32 (None: no RoPE); ``q_norm`` and
    ``k_norm`` are per-head RMSNorm weights (None: no QK-norm). With ``n_kv == 0`` it is
    RoPE (and norm) of a query-only projection; k_out/v_out may then be None.
    ``row_stats``: each row is first scaled by its 1 / rms (``RowStats.rstd(row_eps)``): the
    QKV GEMM ran on the un-normalised input with the norm weight folded into its weight.
    """
    if not triton_enabled(qkv):
        rs = row_stats.rstd(row_eps) if row_stats is not None else None
        return _split_qkv_ref(qkv, n_q, n_kv, head_dim, cos, sin, q_norm, k_norm, eps, k_out, v_out, rs)
    b, s, width = qkv.shape
    assert width == (n_q + 2 * n_kv) * head_dim and qkv.stride(2) == 1 and qkv.stride(0) == s * qkv.stride(1)
    if n_kv == 0:
        k_out = v_out = qkv.new_empty(1, 1, 1, 1)
    assert k_out.stride(3) == 1 and v_out.stride(3) == 1
    q = torch.empty(b, s, n_q, head_dim, device=qkv.device, dtype=qkv.dtype)
    half = head_dim // 2
    rope = cos is not None
    if rope:
        assert cos.stride(2) == 1 and cos.dtype == torch.float32 and cos.stride() == sin.stride()
        cos_sb = cos.stride(0) if cos.shape[0] > 1 else 0
        cos_ss = cos.stride(1)
    else:
        cos = sin = qkv
        cos_sb = cos_ss = 0
    qknorm = q_norm is not None
    grid = (b * s, n_q + 2 * n_kv)
    _split_qkv_kernel[grid](
        qkv, cos, sin, q_norm if qknorm else qkv, k_norm if qknorm else qkv, q, k_out, v_out,
        s, n_q, n_kv, qkv.stride(1), cos_sb, cos_ss,
        q.stride(0), q.stride(1), q.stride(2),
        k_out.stride(0), k_out.stride(2), k_out.stride(1),
        v_out.stride(0), v_out.stride(2), v_out.stride(1), eps,
        *_row_args(row_stats, b * s, row_eps, qkv),
        HALF=half, BLOCK=triton.next_power_of_2(half), ROPE=rope, QKNORM=qknorm,
        ROWSCALE=row_stats is not None, TILES=_tiles(row_stats),
        num_warps=1 if half <= 64 else 2,
    )
    return q


def _row_args(stats: RowStats | None, rows: int, eps: float, dummy: torch.Tensor) -> tuple:
    if stats is None:
        return dummy, 0, rows, 0.0, eps
    assert stats.ss.shape[1] == rows and stats.ss.is_contiguous(), "row stats of another tensor"
    return stats.ss, stats.ss.shape[0], rows, 1.0 / stats.width, eps


def _tiles(stats: RowStats | None) -> int:
    return triton.next_power_of_2(stats.ss.shape[0]) if stats is not None else 1


def resize_table(table: torch.Tensor, grid: int, size: int) -> torch.Tensor:
    """A learned ``[grid * grid, C]`` position table resized bilinearly to ``[size * size, C]``
    (``F.interpolate``, align_corners=False), as a ViT does for another patch grid."""
    if not triton_enabled(table):
        t = table.t().reshape(1, -1, grid, grid)
        return F.interpolate(t, size=(size, size), mode="bilinear", align_corners=False)[0].flatten(1).t()
    assert table.is_contiguous() and table.shape[0] == grid * grid
    c = table.shape[1]
    out = torch.empty(size * size, c, device=table.device, dtype=table.dtype)
    block = min(1024, triton.next_power_of_2(c))
    _resize_table_kernel[(size * size, triton.cdiv(c, block))](table, out, grid, size, c, grid / size,
                                                             BLOCK_C=block, num_warps=4)
    return out


def gated_act(x: torch.Tensor, act: str, row_stats: RowStats | None = None, row_eps: float = 1e-6) -> torch.Tensor:
    """``act(gate) * up`` for ``x = [..., 2F]`` laid out as [gate | up]; act: gelu_tanh or silu.
    ``row_stats``: gate and up are first scaled by their row's 1 / rms (see ``split_qkv``)."""
    if not triton_enabled(x):
        return _gated_act_ref(x, act, row_stats.rstd(row_eps) if row_stats is not None else None)
    n = x.shape[-1] // 2
    x2 = unit_last(x.reshape(-1, 2 * n))
    out = torch.empty(x2.shape[0], n, device=x.device, dtype=x.dtype)
    block = min(1024, triton.next_power_of_2(n))
    _gated_act_kernel[(x2.shape[0], math.ceil(n / block))](
        x2, out, n, x2.stride(0), out.stride(0), *_row_args(row_stats, x2.shape[0], row_eps, x2),
        BLOCK=block, GELU=act == "gelu_tanh", ROWSCALE=row_stats is not None, TILES=_tiles(row_stats), num_warps=4)
    return out.view(*x.shape[:-1], n)


# --------------------------------------------------------------------------- skinny GEMMs
#
# The action stages multiply ~50-200 token rows by weights of 1-17 MB: the weights are the
# bytes. Two kinds of Triton kernel for them:
#
# - ``linear_residual_splitk`` (used by pi0's and SmolVLA's action stages): ``residual +
#   x W^T`` with split-K over all SMs. Each program writes its fp32 partial; the last of a
#   tile's programs to arrive (an atomic counter) sums the partials in a fixed order, adds
#   the residual and writes bf16: one launch instead of cuBLAS's GEMM + split-K reduce +
#   the DtoD copy of the residual, and the result does not depend on arrival order (graph
#   replays equal eager bit for bit). H100, batch 1, weights streamed from HBM: pi0 o-proj
#   6.4 us (cuBLAS addmm 7.6), down 9.7 (11.3); SmolVLA o 5.0 (5.7), down 6.8 (7.7).
# - ``norm_linear`` / ``norm_gated_mlp_in`` / ``norm_qkv``: RMSNorm folded into the GEMM
#   (norm weight applied to the A tile as it loads, the row's sum of squares gathered along
#   the K loop, 1/rms applied to the accumulator), with plain, gated-activation or
#   QKV + RoPE + KV-cache epilogues. Exact and tested, but NOT used by the models yet: on
#   the H100 they ran slower than cuBLAS + the separate norm (pi0 gate/up 17-22 us vs
#   11.4 + 2.5; QKV 17 vs 10.3). They reach ~1 TB/s: too few weight bytes in flight per SM
#   and the A tile re-read by every program. Kept as the starting point for that work.
#
# Counters live in a per-call ``Workspace`` (zeroed once per stage call, left at zero by
# every kernel), so concurrent graphs of other models or batch sizes never share them.
# No kernel waits on another program: correct on any number of SMs (green contexts).


@dataclass(frozen=True)
class RowStats:
    """Sums of squares of each row of a ``[rows, width]`` tensor, split over column tiles
    (``ss``: ``[tiles, rows]`` fp32), as the split-K residual GEMM leaves them for the RMSNorm
    that reads its output next."""

    ss: torch.Tensor
    width: int

    def rstd(self, eps: float) -> torch.Tensor:
        """1 / rms per row (the reference for the kernels' ``_row_rstd``)."""
        return torch.rsqrt(self.ss.sum(0) / self.width + eps)


class Workspace:
    """Per-stage-call scratch: arrival counters for the single-launch split reductions, and the
    row statistics of the last split-K output that has them."""

    def __init__(self, device: torch.device, size: int = 8192):
        self.size = size
        self._cnt = torch.zeros(size, dtype=torch.int32, device=device)
        self._stats: tuple[torch.Tensor, RowStats] | None = None

    def counters(self, n: int) -> torch.Tensor:
        assert n <= self.size, f"workspace too small: {n} > {self.size}"
        return self._cnt

    def keep_stats(self, out: torch.Tensor, stats: RowStats | None) -> None:
        # One entry, holding ``out`` itself: its memory cannot be reused by another tensor
        # while the entry lives, so an identity match can never pick up stale statistics.
        self._stats = (out, stats) if stats is not None else None

    def stats_of(self, x: torch.Tensor) -> RowStats | None:
        """The row statistics of ``x`` if the split-K GEMM that wrote it left them."""
        return self._stats[1] if self._stats is not None and self._stats[0] is x else None


def unit_last(t: torch.Tensor) -> torch.Tensor:
    """``t`` itself when its last dim is contiguous, else a contiguous copy. The kernels below take
    row strides but index the last dim as contiguous; a transposed view would be read wrongly.
    The models' own calls always pass such tensors, so this costs them no kernel."""
    return t if t.stride(-1) == 1 or t.shape[-1] == 1 else t.contiguous()


def fast_gemm_ok(x: torch.Tensor, rows: int) -> bool:
    """Whether the skinny-GEMM kernels take a call: CUDA, 16-bit, few rows."""
    return triton_enabled(x) and x.dtype in (torch.bfloat16, torch.float16) and rows <= 512


if triton is not None:

    @triton.jit
    def _qkv_pairs_store(acc1, acc2, pid_n, offs_m, mask, S, n_q, n_kv, cos_ptr, sin_ptr, cos_sb, cos_ss,
                        q_ptr, k_ptr, v_ptr, q_sb, q_ss, q_sh, k_sb, k_ss, k_sh, v_sb, v_ss, v_sh,
                        ROPE: tl.constexpr, HALF: tl.constexpr, BN: tl.constexpr, INTERLEAVE: tl.constexpr):
        # Epilogue of a fused QKV GEMM tile whose columns are the interleaved pairs (2j, 2j+1),
        # j = pid_n * BN + [0, BN) within one head (BN divides HALF): RoPE on q and k heads,
        # then the store into q, k or v. INTERLEAVE writes each row's pairs in one contiguous store.
        head = (pid_n * BN) // HALF
        p = pid_n * BN + tl.arange(0, BN) - head * HALF
        bi = offs_m // S
        si = offs_m % S
        y0 = acc1
        y1 = acc2
        if ROPE:
            if head < n_q + n_kv:
                cs = bi[:, None] * cos_sb + si[:, None] * cos_ss + p[None, :]
                c = tl.load(cos_ptr + cs, mask=mask, other=0.0)
                sn = tl.load(sin_ptr + cs, mask=mask, other=0.0)
                y0 = acc1 * c - acc2 * sn
                y1 = acc1 * sn + acc2 * c
        if head < n_q:
            dst = q_ptr + bi * q_sb + si * q_ss + head * q_sh
        elif head < n_q + n_kv:
            dst = k_ptr + bi * k_sb + si * k_ss + (head - n_q) * k_sh
        else:
            dst = v_ptr + bi * v_sb + si * v_ss + (head - n_q - n_kv) * v_sh
        if INTERLEAVE:
            cols = 2 * (pid_n * BN - head * HALF) + tl.arange(0, 2 * BN)
            tl.store(dst[:, None] + cols[None, :], tl.interleave(y0, y1).to(q_ptr.dtype.element_ty), mask=mask)
        else:
            tl.store(dst[:, None] + 2 * p[None, :], y0.to(q_ptr.dtype.element_ty), mask=mask)
            tl.store(dst[:, None] + 2 * p[None, :] + 1, y1.to(q_ptr.dtype.element_ty), mask=mask)

    @triton.jit
    def _norm_gemm_kernel(x_ptr, nw_ptr, w_ptr, bias_ptr, out_ptr, cos_ptr, sin_ptr, q_ptr, k_ptr, v_ptr,
                          M, K, N1, S, stride_x, stride_w, stride_o, row2_off, eps,
                          n_q, n_kv, cos_sb, cos_ss, q_sb, q_ss, q_sh, k_sb, k_ss, k_sh, v_sb, v_ss, v_sh,
                          MODE: tl.constexpr, NORM: tl.constexpr, HAS_BIAS: tl.constexpr, ROPE: tl.constexpr,
                          HALF: tl.constexpr, BM: tl.constexpr, BN: tl.constexpr, BK: tl.constexpr):
        # MODE 0: plain; 1: gated GELU(tanh); 2: gated SiLU; 3: QKV split with RoPE.
        pid_m = tl.program_id(0)
        pid_n = tl.program_id(1)
        offs_m = pid_m * BM + tl.arange(0, BM)
        m_ok = offs_m < M
        j = pid_n * BN + tl.arange(0, BN)  # output unit: column (0), gate/up column (1, 2), pair (3)
        j_ok = j < N1
        if MODE == 3:
            rows1 = 2 * j
            rows2 = 2 * j + 1
        else:
            rows1 = j
            rows2 = j + row2_off
        acc1 = tl.zeros([BM, BN], tl.float32)
        acc2 = tl.zeros([BM, BN], tl.float32)
        ss = tl.zeros([BM], tl.float32)
        for k0 in range(0, K, BK):
            offs_k = k0 + tl.arange(0, BK)
            k_ok = offs_k < K
            a = tl.load(x_ptr + offs_m[:, None] * stride_x + offs_k[None, :], mask=m_ok[:, None] & k_ok[None, :],
                        other=0.0)
            if NORM:
                af = a.to(tl.float32)
                ss += tl.sum(af * af, 1)
                nw = tl.load(nw_ptr + offs_k, mask=k_ok, other=0.0).to(tl.float32)
                a = (af * nw[None, :]).to(w_ptr.dtype.element_ty)
            w1 = tl.load(w_ptr + rows1[:, None] * stride_w + offs_k[None, :], mask=j_ok[:, None] & k_ok[None, :],
                         other=0.0)
            acc1 = tl.dot(a, tl.trans(w1), acc1)
            if MODE != 0:
                w2 = tl.load(w_ptr + rows2[:, None] * stride_w + offs_k[None, :],
                             mask=j_ok[:, None] & k_ok[None, :], other=0.0)
                acc2 = tl.dot(a, tl.trans(w2), acc2)
        if NORM:
            r = tl.rsqrt(ss / K + eps)
            acc1 = acc1 * r[:, None]
            acc2 = acc2 * r[:, None]
        mask = m_ok[:, None] & j_ok[None, :]
        if MODE == 0:
            if HAS_BIAS:
                acc1 += tl.load(bias_ptr + j, mask=j_ok, other=0.0).to(tl.float32)[None, :]
            tl.store(out_ptr + offs_m[:, None] * stride_o + j[None, :], acc1.to(out_ptr.dtype.element_ty), mask=mask)
        elif MODE == 3:
            _qkv_pairs_store(acc1, acc2, pid_n, offs_m, mask, S, n_q, n_kv, cos_ptr, sin_ptr, cos_sb, cos_ss,
                            q_ptr, k_ptr, v_ptr, q_sb, q_ss, q_sh, k_sb, k_ss, k_sh, v_sb, v_ss, v_sh,
                            ROPE, HALF, BN, False)
        else:
            if MODE == 1:
                g = acc1.to(out_ptr.dtype.element_ty).to(tl.float32)
                act = g * tl.sigmoid(1.5957691216057308 * (g + 0.044715 * g * g * g))
            else:
                g = acc1.to(out_ptr.dtype.element_ty).to(tl.float32)
                act = g * tl.sigmoid(g)
            u = acc2.to(out_ptr.dtype.element_ty).to(tl.float32)
            tl.store(out_ptr + offs_m[:, None] * stride_o + j[None, :], (act * u).to(out_ptr.dtype.element_ty),
                     mask=mask)

    @triton.jit
    def _gemm_res_kernel(x_ptr, w_ptr, res_ptr, bias_ptr, out_ptr, part_ptr, cnt_ptr, ss_ptr, M, N, K, k_chunk,
                         stride_x, stride_w, stride_r, stride_o,
                         HAS_BIAS: tl.constexpr, SPLIT: tl.constexpr, BM: tl.constexpr, BN: tl.constexpr,
                         BK: tl.constexpr, STATS: tl.constexpr):
        pid_m = tl.program_id(0)
        pid_n = tl.program_id(1)
        pid_s = tl.program_id(2)
        offs_m = pid_m * BM + tl.arange(0, BM)
        offs_n = pid_n * BN + tl.arange(0, BN)
        m_ok = offs_m < M
        n_ok = offs_n < N
        acc = tl.zeros([BM, BN], tl.float32)
        lo = pid_s * k_chunk
        for k0 in range(lo, lo + k_chunk, BK):
            offs_k = k0 + tl.arange(0, BK)
            k_ok = offs_k < K
            a = tl.load(x_ptr + offs_m[:, None] * stride_x + offs_k[None, :], mask=m_ok[:, None] & k_ok[None, :],
                        other=0.0)
            w = tl.load(w_ptr + offs_n[:, None] * stride_w + offs_k[None, :], mask=n_ok[:, None] & k_ok[None, :],
                        other=0.0)
            acc = tl.dot(a, tl.trans(w), acc)
        mask = m_ok[:, None] & n_ok[None, :]
        if SPLIT > 1:
            tile = pid_m * tl.num_programs(1) + pid_n
            loc = tl.arange(0, BM)[:, None] * BN + tl.arange(0, BN)[None, :]
            tl.store(part_ptr + (tile * SPLIT + pid_s) * BM * BN + loc, acc)
            tl.debug_barrier()
            if tl.atomic_add(cnt_ptr + tile, 1, sem="acq_rel", scope="gpu") == SPLIT - 1:
                acc = tl.zeros([BM, BN], tl.float32)
                for sp in tl.static_range(SPLIT):
                    acc += tl.load(part_ptr + (tile * SPLIT + sp) * BM * BN + loc, cache_modifier=".cg")
                if HAS_BIAS:
                    acc += tl.load(bias_ptr + offs_n, mask=n_ok, other=0.0).to(tl.float32)[None, :]
                acc += tl.load(res_ptr + offs_m[:, None] * stride_r + offs_n[None, :], mask=mask, other=0.0).to(tl.float32)
                _store_res_tile(acc, out_ptr, ss_ptr, offs_m, offs_n, m_ok, mask, pid_n, M, stride_o, STATS)
                tl.atomic_xchg(cnt_ptr + tile, 0, sem="relaxed", scope="gpu")
        else:
            if HAS_BIAS:
                acc += tl.load(bias_ptr + offs_n, mask=n_ok, other=0.0).to(tl.float32)[None, :]
            acc += tl.load(res_ptr + offs_m[:, None] * stride_r + offs_n[None, :], mask=mask, other=0.0).to(tl.float32)
            _store_res_tile(acc, out_ptr, ss_ptr, offs_m, offs_n, m_ok, mask, pid_n, M, stride_o, STATS)

    @triton.jit
    def _store_res_tile(acc, out_ptr, ss_ptr, offs_m, offs_n, m_ok, mask, pid_n, M, stride_o, STATS: tl.constexpr):
        y = acc.to(out_ptr.dtype.element_ty)
        tl.store(out_ptr + offs_m[:, None] * stride_o + offs_n[None, :], y, mask=mask)
        if STATS:  # the next RMSNorm's sums of squares, of the values as stored
            yf = tl.where(mask, y.to(tl.float32), 0.0)
            tl.store(ss_ptr + pid_n * M + offs_m, tl.sum(yf * yf, 1), mask=m_ok)


# Tunables (the GPU bench script overrides them to compare variants).
# (BK 64, 4 stages, 4 warps, 32-wide N tiles, about one program per SM: best of the variants
# timed on the H100 for pi0's and SmolVLA's o / down projections, see docs/RESULTS.md.)
GEMM_CFG = {"bk": 64, "warps": 4, "stages": 4, "target": 1.0, "res_bn": 32, "bn": None, "split": None,
            "res_bk": None, "res_stages": None, "res_warps": None, "max_rows": 128, "min_bytes_over_64_rows": 4e6, "stats_over_64_rows": True}


def _block_m(rows: int) -> int:
    return max(16, min(128, triton.next_power_of_2(rows)))


def _pick_bn(units: int, m_tiles: int, sm: int, choices=(64, 32, 16)) -> int:
    """The widest dot tile that still gives about one program per SM."""
    if GEMM_CFG["bn"] and GEMM_CFG["bn"] in choices:
        return GEMM_CFG["bn"]
    for bn in choices:
        if m_tiles * triton.cdiv(units, bn) >= GEMM_CFG["target"] * sm:
            return bn
    return choices[-1]


def _norm_linear_ref(x, norm_w, eps, weight, bias):
    h = F.rms_norm(x, (x.shape[-1],), norm_w, eps) if norm_w is not None else x
    return F.linear(h, weight, bias)


def norm_linear(x: torch.Tensor, norm_w: torch.Tensor | None, eps: float, weight: torch.Tensor,
                bias: torch.Tensor | None = None, ws: Workspace | None = None) -> torch.Tensor:
    """``linear(rms_norm(x) * norm_w)`` (``norm_w`` None: no norm) -> ``[..., N]``."""
    rows = x.numel() // x.shape[-1]
    if not fast_gemm_ok(x, rows):
        return _norm_linear_ref(x, norm_w, eps, weight, bias)
    k = x.shape[-1]
    x2, weight = unit_last(x.reshape(rows, k)), unit_last(weight)
    n = weight.shape[0]
    out = torch.empty(rows, n, device=x.device, dtype=x.dtype)
    bm = _block_m(rows)
    grid_m = triton.cdiv(rows, bm)
    bn = _pick_bn(n, grid_m, _sm_count(x.device))
    _norm_gemm_kernel[(grid_m, triton.cdiv(n, bn))](
        x2, norm_w if norm_w is not None else x2, weight, bias if bias is not None else x2, out, x2, x2, x2, x2, x2,
        rows, k, n, 1, x2.stride(0), weight.stride(0), out.stride(0), 0, eps,
        0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0,
        MODE=0, NORM=norm_w is not None, HAS_BIAS=bias is not None, ROPE=False, HALF=1,
        BM=bm, BN=bn, BK=GEMM_CFG["bk"], num_warps=GEMM_CFG["warps"], num_stages=GEMM_CFG["stages"])
    return out.view(*x.shape[:-1], n)


def norm_gated_mlp_in(x: torch.Tensor, norm_w: torch.Tensor | None, eps: float, weight: torch.Tensor,
                      act: str, ws: Workspace | None = None) -> torch.Tensor:
    """``act(h Wg^T) * (h Wu^T)`` with ``h = rms_norm(x) * norm_w`` and ``weight = [Wg; Wu]``."""
    rows = x.numel() // x.shape[-1]
    if not fast_gemm_ok(x, rows):
        return _gated_act_ref(_norm_linear_ref(x, norm_w, eps, weight, None), act)
    k = x.shape[-1]
    x2, weight = unit_last(x.reshape(rows, k)), unit_last(weight)
    f = weight.shape[0] // 2
    out = torch.empty(rows, f, device=x.device, dtype=x.dtype)
    bm = _block_m(rows)
    grid_m = triton.cdiv(rows, bm)
    bn = _pick_bn(f, grid_m, _sm_count(x.device), (32, 16))
    _norm_gemm_kernel[(grid_m, triton.cdiv(f, bn))](
        x2, norm_w if norm_w is not None else x2, weight, x2, out, x2, x2, x2, x2, x2,
        rows, k, f, 1, x2.stride(0), weight.stride(0), out.stride(0), f, eps,
        0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0,
        MODE=1 if act == "gelu_tanh" else 2, NORM=norm_w is not None, HAS_BIAS=False, ROPE=False, HALF=1,
        BM=bm, BN=bn, BK=GEMM_CFG["bk"], num_warps=GEMM_CFG["warps"], num_stages=GEMM_CFG["stages"])
    return out.view(*x.shape[:-1], f)


def norm_qkv(x: torch.Tensor, norm_w: torch.Tensor, eps: float, weight: torch.Tensor, n_q: int, n_kv: int,
             head_dim: int, k_out: torch.Tensor | None, v_out: torch.Tensor | None,
             cos: torch.Tensor | None, sin: torch.Tensor | None, ws: Workspace | None = None) -> torch.Tensor:
    """``split_qkv(linear(rms_norm(x) * norm_w, weight), ...)`` in one kernel: returns q
    ``[B, S, n_q, D]`` and writes k / v into ``k_out`` / ``v_out`` (no bias, no QK-norm)."""
    b, s, k = x.shape
    rows = b * s
    if not fast_gemm_ok(x, rows):
        qkv = _norm_linear_ref(x, norm_w, eps, weight, None)
        return _split_qkv_ref(qkv, n_q, n_kv, head_dim, cos, sin, None, None, eps, k_out, v_out)
    assert weight.shape[0] == (n_q + 2 * n_kv) * head_dim and x.stride(2) == 1 and x.stride(0) == s * x.stride(1)
    weight = unit_last(weight)
    q = torch.empty(b, s, n_q, head_dim, device=x.device, dtype=x.dtype)
    if n_kv == 0:
        k_out = v_out = q
        k_st = v_st = (0, 0, 0)
    else:
        assert k_out.stride(3) == 1 and v_out.stride(3) == 1
        k_st = (k_out.stride(0), k_out.stride(2), k_out.stride(1))
        v_st = (v_out.stride(0), v_out.stride(2), v_out.stride(1))
    rope = cos is not None
    if rope:
        assert cos.stride(2) == 1 and cos.dtype == torch.float32 and cos.stride() == sin.stride()
        cos_sb, cos_ss = (cos.stride(0) if cos.shape[0] > 1 else 0), cos.stride(1)
    else:
        cos = sin = x
        cos_sb = cos_ss = 0
    half = head_dim // 2
    pairs = weight.shape[0] // 2
    bm = _block_m(rows)
    grid_m = triton.cdiv(rows, bm)
    bn = _pick_bn(pairs, grid_m, _sm_count(x.device), tuple(c for c in (64, 32, 16) if half % c == 0) or (16,))
    assert half % bn == 0
    _norm_gemm_kernel[(grid_m, pairs // bn)](
        x, norm_w, weight, x, q, cos, sin, q, k_out, v_out,
        rows, k, pairs, s, x.stride(1), weight.stride(0), 0, 0, eps,
        n_q, n_kv, cos_sb, cos_ss, q.stride(0), q.stride(1), q.stride(2), *k_st, *v_st,
        MODE=3, NORM=True, HAS_BIAS=False, ROPE=rope, HALF=half,
        BM=bm, BN=bn, BK=GEMM_CFG["bk"], num_warps=GEMM_CFG["warps"], num_stages=GEMM_CFG["stages"])
    return q


def addmm_residual(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, residual: torch.Tensor,
                   inplace: bool = False) -> torch.Tensor:
    """``residual + linear(x, weight, bias)`` on cuBLAS: the GEMM adds the residual, then the bias is
    added. ``addmm`` writes into a copy of the residual (a DtoD copy); with ``inplace`` (the caller
    does not need ``residual`` afterwards) the GEMM accumulates into ``residual`` itself, when it is
    contiguous and autograd does not need its old value (a stage run with gradients on, in a test)."""
    n, k = weight.shape
    r2, x2 = residual.reshape(-1, n), x.reshape(-1, k)
    inplace = inplace and residual.is_contiguous() and not (residual.requires_grad and torch.is_grad_enabled())
    out = r2.addmm_(x2, weight.t()) if inplace else torch.addmm(r2, x2, weight.t())
    if bias is not None:
        out += bias
    return out.view(residual.shape)


def linear_residual_splitk(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, residual: torch.Tensor,
                           ws: Workspace | None, stats: bool = False) -> torch.Tensor:
    """``residual + linear(x, weight, bias)`` (bf16 out, fp32 accumulation, one launch).

    The cuBLAS fallback accumulates into ``residual`` in place (``addmm_residual``): callers pass a
    residual they do not need afterwards.

    ``stats``: the last program of each column tile also writes its rows' sums of squares, kept
    in ``ws`` for the output (``Workspace.stats_of``), so the RMSNorm that reads it next needs no
    kernel of its own. Only the Triton path leaves them; on the cuBLAS path there are none."""
    n, k = weight.shape
    rows = residual.numel() // n
    # Over 64 rows the A tile re-read by every N tile costs more than the small weights save:
    # measured slower than cuBLAS for SmolVLA at batch 2 (1.4 / 2.9 MB: 0.4 ms over the stage),
    # faster for pi0 (4.2 / 8.4 MB). With row statistics wanted it pays anyway, because the norm
    # after it then folds away: SmolVLA's stage at batch 2 is 0.55 ms faster (norm_fold_ab.py).
    big_enough = (rows <= 64 or (stats and GEMM_CFG["stats_over_64_rows"])
                  or weight.numel() * weight.element_size() >= GEMM_CFG["min_bytes_over_64_rows"])
    if ws is None or not fast_gemm_ok(x, rows) or rows > GEMM_CFG["max_rows"] or not big_enough:
        out = addmm_residual(x, weight, bias, residual, inplace=True)  # the callers drop their residual
        if ws is not None:
            ws.keep_stats(out, None)
        return out
    x2, weight, r2 = unit_last(x.reshape(rows, k)), unit_last(weight), unit_last(residual.reshape(rows, n))
    out = torch.empty(rows, n, device=x.device, dtype=residual.dtype)
    bm = _block_m(rows)
    bn = GEMM_CFG["res_bn"]
    bk = GEMM_CFG["res_bk"] or GEMM_CFG["bk"]
    grid_m, grid_n = triton.cdiv(rows, bm), triton.cdiv(n, bn)
    sm = _sm_count(x.device)
    split = GEMM_CFG["split"] or round(GEMM_CFG["target"] * sm / (grid_m * grid_n))
    split = max(1, min(split, triton.cdiv(k, bk), 16))
    chunk = triton.cdiv(triton.cdiv(k, split), bk) * bk
    split = triton.cdiv(k, chunk)
    if split > 1:
        part = torch.empty(grid_m * grid_n * split * bm * bn, device=x.device, dtype=torch.float32)
        cnt = ws.counters(grid_m * grid_n)
    else:
        part = cnt = out
    ss = torch.empty(grid_n, rows, device=x.device, dtype=torch.float32) if stats else out
    _gemm_res_kernel[(grid_m, grid_n, split)](
        x2, weight, r2, bias if bias is not None else x2, out, part, cnt, ss, rows, n, k, chunk,
        x2.stride(0), weight.stride(0), r2.stride(0), out.stride(0),
        HAS_BIAS=bias is not None, SPLIT=split, BM=bm, BN=bn, BK=bk, STATS=stats,
        num_warps=GEMM_CFG["res_warps"] or GEMM_CFG["warps"], num_stages=GEMM_CFG["res_stages"] or GEMM_CFG["stages"])
    result = out.view(residual.shape)
    ws.keep_stats(result, RowStats(ss, n) if stats else None)
    return result

