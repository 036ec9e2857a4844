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


def _split_qkv_ref(qkv, n_q, n_kv, head_dim, cos, sin, q_norm, k_norm, eps, k_out, v_out):
    b, s, _ = qkv.shape
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


def _gated_act_ref(x: torch.Tensor, act: str) -> torch.Tensor:
    gate, up = x.chunk(2, dim=-1)
    gate = F.gelu(gate, approximate="tanh") if act == "gelu_tanh" else F.silu(gate)
    return gate * up


# --------------------------------------------------------------------------- Triton

if triton is not None:

    @triton.jit
    def _split_qkv_kernel(
        qkv_ptr, cos_ptr, sin_ptr, qn_ptr, kn_ptr, q_ptr, k_ptr, v_ptr,
        S, n_q, n_kv, stride_row, cos_sb, cos_ss,
        q_sb, q_ss, q_sh, k_sb, k_ss, k_sh, v_sb, v_ss, v_sh, eps,
        HALF: tl.constexpr, BLOCK: tl.constexpr, ROPE: tl.constexpr, QKNORM: tl.constexpr,
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
    def _gated_act_kernel(x_ptr, out_ptr, n_cols, stride_x, stride_o, BLOCK: tl.constexpr, GELU: tl.constexpr):
        row = tl.program_id(0)
        col = tl.program_id(1) * BLOCK + tl.arange(0, BLOCK)
        m = col < n_cols
        g = tl.load(x_ptr + row * stride_x + col, mask=m, other=0.0).to(tl.float32)
        u = tl.load(x_ptr + row * stride_x + n_cols + col, mask=m, other=0.0).to(tl.float32)
        if GELU:
            # 0.5 * (1 + tanh(z)) == sigmoid(2z)
            a = g * tl.sigmoid(1.5957691216057308 * (g + 0.044715 * g * g * g))
        else:
            a = g * tl.sigmoid(g)
        tl.store(out_ptr + row * stride_o + col, (a * u).to(out_ptr.dtype.element_ty), mask=m)


    @triton.jit
    def _attn_kernel(q_ptr, k_ptr, v_ptr, bias_ptr, o_ptr, part_ptr, ml_ptr, M, L, H, split_len, sm_scale,
                     q_sb, q_sh, q_sm, k_sb, k_sh, k_sl, v_sb, v_sh, v_sl, b_sb, b_sm, o_sb, o_sh, o_sm,
                     HAS_BIAS: tl.constexpr, SPLIT: tl.constexpr, D: tl.constexpr, BLOCK_M: tl.constexpr,
                     BLOCK_N: tl.constexpr):
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


# --------------------------------------------------------------------------- API


def attention_fits(q: torch.Tensor, rows: int, head_dim: int) -> bool:
    """Whether the Triton attention kernel takes this call: few query rows per KV head (the
    action stages), where library kernels leave most SMs idle (one program per 128 rows)."""
    return triton_enabled(q) and head_dim in (64, 128, 256) and rows <= 1024 and q.dtype != torch.float32


def small_attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """q ``[B, H, M, D]`` (any strides, last dim contiguous), k/v ``[B, H, L, D]``, bias additive
    ``[B or 1, 1, M or 1, L]`` -> out ``[B, M, H, D]`` memory order, returned as ``[B, H, M, D]``."""
    b, h, m, d = q.shape
    length = k.shape[2]
    out = torch.empty(b, m, h, d, device=q.device, dtype=q.dtype).transpose(1, 2)
    block_m = 16
    has_bias = bias is not None
    if has_bias:
        b_sb = bias.stride(0) if bias.shape[0] > 1 else 0
        b_sm = bias.stride(2) if bias.shape[2] > 1 else 0
    else:
        bias, b_sb, b_sm = q, 0, 0
    block_n = 64 if d <= 128 else 32
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
    _attn_kernel[grid](q, k, v, bias, out, part, ml, m, length, h, split_len, d ** -0.5,
                       q.stride(0), q.stride(1), q.stride(2), k.stride(0), k.stride(1), k.stride(2),
                       v.stride(0), v.stride(1), v.stride(2), b_sb, b_sm, out.stride(0), out.stride(1), out.stride(2),
                       HAS_BIAS=has_bias, SPLIT=split, D=d, BLOCK_M=block_m, BLOCK_N=block_n,
                       num_warps=4, num_stages=2)
    if split:
        _attn_combine[(b * h, triton.cdiv(m, block_m))](part, ml, out, m, h, out.stride(0), out.stride(1),
                                                         out.stride(2), NS=n_split, D=d, BLOCK_M=block_m,
                                                         num_warps=4)
    return out


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
              eps: float = 1e-6) -> torch.Tensor:
    """Split ``qkv [B, S, (n_q + 2 n_kv) * head_dim]`` into heads.

    Returns q as a new ``[B, S, n_q, head_dim]`` tensor; k and v are written into
    ``k_out`` / ``v_out`` (``[B, n_kv, S, head_dim]`` views, e.g. a slice of a KV cache).
    ``cos``/``sin`` are ``[B or 1, S, head_dim / 2]`` fp32 (None: no RoPE); ``q_norm`` and
    ``k_norm`` are per-head RMSNorm weights (None: no QK-norm). With ``n_kv == 0`` it is
    RoPE (and norm) of a query-only projection; k_out/v_out may then be None.
    """
    if not triton_enabled(qkv):
        return _split_qkv_ref(qkv, n_q, n_kv, head_dim, cos, sin, q_norm, k_norm, eps, k_out, v_out)
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
        HALF=half, BLOCK=triton.next_power_of_2(half), ROPE=rope, QKNORM=qknorm,
        num_warps=1 if half <= 64 else 2,
    )
    return q


def gated_act(x: torch.Tensor, act: str) -> torch.Tensor:
    """``act(gate) * up`` for ``x = [..., 2F]`` laid out as [gate | up]; act: gelu_tanh or silu."""
    if not triton_enabled(x):
        return _gated_act_ref(x, act)
    n = x.shape[-1] // 2
    x2 = x.reshape(-1, 2 * n)
    out = torch.empty(x2.shape[0], n, device=x.device, dtype=x.dtype)
    block = min(1024, triton.next_power_of_2(n))
    _gated_act_kernel[(x2.shape[0], math.ceil(n / block))](
        x2, out, n, x2.stride(0), out.stride(0), BLOCK=block, GELU=act == "gelu_tanh", num_warps=4)
    return out.view(*x.shape[:-1], n)
