"""Building blocks shared by the zoo's architectures.

Conventions that every model file relies on:

- Activations are ``[B, S, dim]``; KV caches are ``[B, n_kv, L, head_dim]`` (views into
  bigger buffers are fine).
- Grouped-query attention: query head ``h`` reads KV head ``h % n_kv``. With that
  grouping the query tensor ``[B, S, n_q, D]`` *is* ``[B, S * g, n_kv, D]`` without a
  copy, so GQA/MQA runs as plain multi-head attention over ``n_kv`` heads with a longer
  query axis, and the output comes back already in ``[B, S, n_q * D]`` order. (HF
  checkpoints group as ``h // g``; converting them is a fixed permutation of the q / o
  projection rows.)
- Masks are additive biases built once per stage call (``attn_bias``) with one row per
  folded query row, so SDPA never re-pads or re-converts them inside the layer loop.
- Projections are fused (QKV in one GEMM, gate/up in one GEMM) and residual adds ride
  on the GEMM (``addmm``) to keep the kernel count of the action stages low.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from shared.models.fused import (RowStats, Workspace, addmm_residual, attention_fits, gated_act,  # noqa: F401
                                 gemm_attention, gemm_attention_fits, linear_residual_splitk, small_attention,
                                 split_qkv)

# --------------------------------------------------------------------------- init


@torch.no_grad()
def init_weights(module: nn.Module, generator: torch.Generator) -> None:
    """Seeded random init that keeps activations O(1) through deep random stacks.

    Linear weights ~ N(0, 1/fan_in), embeddings ~ N(0, 1), norms at identity, biases 0,
    any other parameter (learned tokens, position tables, AdaLN tables) ~ N(0, 0.02).
    Same generator state, same device: same weights.
    """
    done: set[int] = set()
    for name, m in module.named_modules():
        if isinstance(m, nn.Linear):
            m.weight.normal_(0.0, 1.0 / math.sqrt(m.in_features), generator=generator)
            if m.bias is not None:
                m.bias.zero_()
        elif isinstance(m, nn.Embedding):
            m.weight.normal_(0.0, 1.0, generator=generator)
        elif hasattr(m, "init_parameters"):  # a module that knows its own fan-in
            m.init_parameters(generator)
        elif isinstance(m, (RMSNorm, nn.LayerNorm)):
            if getattr(m, "weight", None) is not None:
                m.weight.fill_(1.0)
            if getattr(m, "bias", None) is not None:
                m.bias.zero_()
        else:
            continue
        done.update(id(p) for p in m.parameters(recurse=False))
    for p in module.parameters():
        if id(p) not in done:
            p.normal_(0.0, 0.02, generator=generator)


# --------------------------------------------------------------------------- norms


class RMSNorm(nn.Module):
    """y = x / rms(x) * weight. (Gemma stores ``weight - 1``; add 1 when converting.)"""

    def __init__(self, dim: int, eps: float = 1e-6):
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.rms_norm(x, (x.shape[-1],), self.weight, self.eps)


def _version(t: torch.Tensor) -> int:
    try:
        return t._version
    except RuntimeError:  # inference tensors keep no version counter
        return -1


def folded_weight(lin: nn.Linear, norm: RMSNorm) -> torch.Tensor:
    """``lin.weight`` with ``norm.weight`` multiplied into its columns, so that
    ``lin(norm(x)) == (x @ folded.T) / rms(x)`` (no bias). Made on first use and kept on ``lin``
    beside its own parameters, which stay as they are (state dicts and the reference path see
    the model's weights); made again if either weight is replaced or changed in place."""
    key = (lin.weight.data_ptr(), norm.weight.data_ptr(), _version(lin.weight), _version(norm.weight))
    cached = lin.__dict__.get("_folded")
    if cached is None or cached[0] != key:
        if lin.weight.is_cuda and torch.cuda.is_current_stream_capturing():
            # A copy made inside a capture would hold its values only after the first replay.
            raise RuntimeError("folded norm weights are made on the first eager call; run the stage once before "
                               "capturing it")
        with torch.no_grad():
            w = (lin.weight.float() * norm.weight.float()[None, :]).to(lin.weight.dtype)
        lin.__dict__["_folded"] = cached = (key, w)
    return cached[1]


FOLD_NORMS = True  # bench/experiments/norm_fold_ab.py turns it off to time the stages without


def folded_norm_linear(x: torch.Tensor, norm: RMSNorm, lin: nn.Linear,
                ws: Workspace) -> tuple[torch.Tensor, RowStats | None]:
    """``lin(norm(x))`` in the action stages. When the split-K GEMM that wrote ``x`` left its
    rows' sums of squares in ``ws``, the norm's kernel is skipped: the GEMM runs on ``x`` with the
    norm weight folded into its weight, and the returned stats carry the 1 / rms that the
    consumer (``split_qkv`` / ``gated_act``) applies to each row. Otherwise the stats are None
    and the product is already normalised."""
    stats = ws.stats_of(x) if FOLD_NORMS else None
    if stats is None or lin.bias is not None:  # a bias must not be scaled by 1 / rms
        return lin(norm(x)), None
    return F.linear(x, folded_weight(lin, norm)), stats


def ada_layer_norm(x: torch.Tensor, shift: torch.Tensor, scale_plus_one: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """AdaLN: LayerNorm(x) * (1 + scale) + shift as *one* LayerNorm kernel.

    The time t is shared by the whole batch (fixed step schedule), so the modulation is a
    per-channel vector and can be passed as LayerNorm's affine weight and bias. Callers
    precompute ``1 + scale`` for all steps once per call.
    """
    return F.layer_norm(x, (x.shape[-1],), scale_plus_one, shift, eps)


# --------------------------------------------------------------------------- linear helpers


def linear_residual(x: torch.Tensor, lin: nn.Linear, residual: torch.Tensor, ws: Workspace | None = None) -> torch.Tensor:
    """residual + lin(x) with the add done by the GEMM (one kernel when lin has no bias).

    The result may be written into ``residual`` itself: callers pass a residual they do not need
    afterwards (every block here hands on the sum and drops its input). On cuBLAS the GEMM then
    accumulates into it in place; ``addmm`` would first copy it (one DtoD copy per projection).

    With a workspace (the action stages) calls of up to 64 rows take the split-K Triton GEMM, which
    adds bias and residual in its epilogue: one launch instead of GEMM and bias add. Over 64 rows
    every column tile re-reads a larger A tile: GR00T's DiT at batch 2 (98 rows) was slower that way
    (6.31 against 6.25 ms per stage on an H100, bench/experiments/dit_splitk_ab.py), so those stay on
    cuBLAS in place."""
    if ws is not None and residual.numel() // lin.out_features <= 64:
        return linear_residual_splitk(x, lin.weight, lin.bias, residual, ws)
    out = addmm_residual(x, lin.weight, lin.bias, residual, inplace=True)
    if ws is not None:
        ws.keep_stats(out, None)  # ``residual`` may have been the output kept with row statistics: not any more
    return out


class GatedMLP(nn.Module):
    """GeGLU (act="gelu_tanh", Gemma) or SwiGLU (act="silu", Llama/Qwen) with fused gate/up."""

    def __init__(self, dim: int, hidden: int, act: str, bias: bool = False):
        super().__init__()
        self.act = act
        self.gate_up = nn.Linear(dim, 2 * hidden, bias=bias)
        self.down = nn.Linear(hidden, dim, bias=bias)

    def forward(self, x: torch.Tensor, residual: torch.Tensor) -> torch.Tensor:
        return linear_residual(gated_act(self.gate_up(x), self.act), self.down, residual)


class MLP(nn.Module):
    """fc1 -> GELU(tanh) -> fc2 with biases (SigLIP, DiT feed-forward)."""

    def __init__(self, dim: int, hidden: int, out_dim: int | None = None):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, out_dim or dim)

    def forward(self, x: torch.Tensor, residual: torch.Tensor | None = None, ws: Workspace | None = None) -> torch.Tensor:
        h = F.gelu(self.fc1(x), approximate="tanh")
        return self.fc2(h) if residual is None else linear_residual(h, self.fc2, residual, ws)


# --------------------------------------------------------------------------- RoPE / time


def rope_cos_sin(positions: torch.Tensor, head_dim: int, theta: float = 10000.0) -> tuple[torch.Tensor, torch.Tensor]:
    """cos/sin ``[B, S, head_dim/2]`` (fp32) for integer positions ``[B, S]``."""
    half = head_dim // 2
    inv = theta ** (-torch.arange(half, device=positions.device, dtype=torch.float32) / half)
    ang = positions.float()[..., None] * inv
    return ang.cos(), ang.sin()


def rope_cos_sin_2d(rows: torch.Tensor, cols: torch.Tensor, head_dim: int,
                    theta: float = 10000.0) -> tuple[torch.Tensor, torch.Tensor]:
    """2-D RoPE for a ViT patch grid: half of the rotated pairs follow the row, half the column."""
    quarter = head_dim // 4
    inv = theta ** (-torch.arange(quarter, device=rows.device, dtype=torch.float32) / quarter)
    ang = torch.cat([rows.float()[..., None] * inv, cols.float()[..., None] * inv], dim=-1)
    return ang.cos(), ang.sin()


def sincos_time(t: torch.Tensor, dim: int, min_period: float = 4e-3, max_period: float = 4.0) -> torch.Tensor:
    """pi0 / SmolVLA time embedding: [sin | cos] of t at geometrically spaced periods. t: [N] -> [N, dim]."""
    frac = torch.linspace(0.0, 1.0, dim // 2, device=t.device, dtype=torch.float32)
    period = min_period * (max_period / min_period) ** frac
    ang = t.float()[:, None] * (2 * math.pi / period)
    return torch.cat([ang.sin(), ang.cos()], dim=-1)


def timestep_embedding(t: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """DiT / diffusers sinusoidal embedding [cos | sin] of (already scaled) timesteps. t: [N] -> [N, dim]."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    ang = t.float()[:, None] * freqs
    return torch.cat([ang.cos(), ang.sin()], dim=-1)


def euler_times(steps: int, device: torch.device) -> torch.Tensor:
    """Flow-matching times t_0 = 1 > t_1 > ... > t_{steps-1} (dt = -1/steps)."""
    return 1.0 - torch.arange(steps, device=device, dtype=torch.float32) / steps


# --------------------------------------------------------------------------- attention


def attn_bias(allowed: torch.Tensor, groups: int, dtype: torch.dtype) -> torch.Tensor:
    """Additive SDPA mask from a boolean ``allowed [B or 1, S or 1, L]``.

    Returns ``[B or 1, 1, S * groups or 1, L]``: rows repeated for the folded GQA query
    axis. The last dim is stored padded to a multiple of 16 so the memory-efficient
    kernel takes it as is, with no per-layer copy.
    """
    b, s, length = allowed.shape
    if s > 1 and groups > 1:
        allowed = allowed.repeat_interleave(groups, dim=1)
    rows = allowed.shape[1]
    padded = -(-length // 16) * 16
    store = torch.zeros(b, 1, rows, padded, device=allowed.device, dtype=dtype)
    bias = store[..., :length]
    bias.masked_fill_(~allowed[:, None], torch.finfo(dtype).min)
    return bias


def attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, bias: torch.Tensor | None = None,
              ws: Workspace | None = None) -> torch.Tensor:
    """q ``[B, S, n_q, D]``, k/v ``[B, n_kv, L, D]`` -> ``[B, S, n_q * D]`` (head h reads KV h % n_kv)."""
    b, s, n_q, d = q.shape
    n_kv = k.shape[1]
    qh = q.reshape(b, s * (n_q // n_kv), n_kv, d).transpose(1, 2)
    if attention_fits(q, qh.shape[2], d, b * n_kv):
        o = small_attention(qh, k, v, bias, ws)
    elif gemm_attention_fits(q, qh.shape[2], k.shape[2], d, b * n_kv):
        o = gemm_attention(qh, k, v, bias)
    else:
        o = F.scaled_dot_product_attention(qh, k, v, attn_mask=bias)
    return o.transpose(1, 2).reshape(b, s, n_q * d)


class Attention(nn.Module):
    """Self-attention projections: one fused QKV GEMM, optional QK RMSNorm, output projection."""

    def __init__(self, dim: int, n_heads: int, n_kv_heads: int, head_dim: int, bias: bool = False,
                 out_bias: bool | None = None, qk_norm: bool = False, out_dim: int | None = None, eps: float = 1e-6):
        super().__init__()
        self.n_heads, self.n_kv_heads, self.head_dim, self.eps = n_heads, n_kv_heads, head_dim, eps
        self.qkv = nn.Linear(dim, (n_heads + 2 * n_kv_heads) * head_dim, bias=bias)
        self.o = nn.Linear(n_heads * head_dim, out_dim or dim, bias=bias if out_bias is None else out_bias)
        self.q_norm = RMSNorm(head_dim, eps) if qk_norm else None
        self.k_norm = RMSNorm(head_dim, eps) if qk_norm else None

    def project(self, x: torch.Tensor, k_out: torch.Tensor, v_out: torch.Tensor,
                rope: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """Returns q ``[B, S, n_q, D]``; writes (post-norm, post-RoPE) k and v into ``k_out``/``v_out``."""
        cos, sin = rope if rope is not None else (None, None)
        qn = self.q_norm.weight if self.q_norm is not None else None
        kn = self.k_norm.weight if self.k_norm is not None else None
        return split_qkv(self.qkv(x), self.n_heads, self.n_kv_heads, self.head_dim, k_out, v_out,
                         cos, sin, qn, kn, self.eps)

    def new_kv(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, s = x.shape[:2]
        kv = torch.empty(2, b, self.n_kv_heads, s, self.head_dim, device=x.device, dtype=x.dtype)
        return kv[0], kv[1]


class CrossAttention(nn.Module):
    """Queries from the sequence, keys/values from a fixed context; K/V are computed once per call."""

    def __init__(self, dim: int, ctx_dim: int, n_heads: int, head_dim: int, bias: bool = True):
        super().__init__()
        self.n_heads, self.head_dim = n_heads, head_dim
        self.q = nn.Linear(dim, n_heads * head_dim, bias=bias)
        self.kv = nn.Linear(ctx_dim, 2 * n_heads * head_dim, bias=bias)
        self.o = nn.Linear(n_heads * head_dim, dim, bias=bias)

    def context_kv(self, ctx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, length = ctx.shape[:2]
        kv = self.kv(ctx).view(b, length, 2, self.n_heads, self.head_dim).permute(2, 0, 3, 1, 4).contiguous()
        return kv[0], kv[1]

    def forward(self, x: torch.Tensor, kv: tuple[torch.Tensor, torch.Tensor], bias: torch.Tensor | None,
                residual: torch.Tensor, ws: Workspace | None = None) -> torch.Tensor:
        q = self.q(x).unflatten(-1, (self.n_heads, self.head_dim))
        return linear_residual(attention(q, kv[0], kv[1], bias, ws), self.o, residual, ws)


# --------------------------------------------------------------------------- vision


def images_to_patches(images: torch.Tensor, size: int, patch: int, dtype: torch.dtype) -> torch.Tensor:
    """uint8 ``[B, cams, H, W, 3]`` -> normalised patches ``[B * cams, (size/patch)^2, patch*patch*3]``.

    Resizes on the device only when the wire size differs from the model's input size.
    Patch vectors are (row, col, channel) ordered, i.e. channels-last like the wire.
    """
    x = images.flatten(0, 1)
    n, h, w, _ = x.shape
    if h != size or w != size:
        x = F.interpolate(x.permute(0, 3, 1, 2).to(dtype), size=(size, size), mode="bilinear",
                          align_corners=False).permute(0, 2, 3, 1)
    g = size // patch
    x = x.reshape(n, g, patch, g, patch, 3).transpose(2, 3).reshape(n, g * g, patch * patch * 3)
    return x.to(dtype).mul_(2.0 / 255.0).sub_(1.0)


class ViTBlock(nn.Module):
    """Pre-LN ViT block (SigLIP / Qwen-VL vision): biased fused QKV, GELU(tanh) MLP."""

    def __init__(self, dim: int, heads: int, mlp: int, eps: float = 1e-6):
        super().__init__()
        self.heads, self.head_dim = heads, dim // heads
        self.norm1 = nn.LayerNorm(dim, eps=eps)
        self.attn = Attention(dim, heads, heads, dim // heads, bias=True)
        self.norm2 = nn.LayerNorm(dim, eps=eps)
        self.mlp = MLP(dim, mlp)

    def forward(self, x: torch.Tensor, rope: tuple[torch.Tensor, torch.Tensor] | None = None,
                bias: torch.Tensor | None = None) -> torch.Tensor:
        n, s, _ = x.shape
        h = self.norm1(x)
        if rope is None:
            q, k, v = self.attn.qkv(h).view(n, s, 3, self.heads, self.head_dim).unbind(2)
            k, v = k.transpose(1, 2), v.transpose(1, 2)
        else:
            k, v = self.attn.new_kv(h)
            q = self.attn.project(h, k, v, rope)
        x = linear_residual(attention(q, k, v, bias), self.attn.o, x)
        return self.mlp(self.norm2(x), x)


class SigLIP(nn.Module):
    """SigLIP-style ViT: linear patch embedding, learned positions, pre-LN blocks, final LayerNorm."""

    def __init__(self, image_size: int, patch: int, width: int, depth: int, heads: int, mlp: int):
        super().__init__()
        self.image_size, self.patch = image_size, patch
        self.patch_embed = nn.Linear(patch * patch * 3, width)
        self.pos_embed = nn.Parameter(torch.zeros((image_size // patch) ** 2, width))
        self.blocks = nn.ModuleList(ViTBlock(width, heads, mlp) for _ in range(depth))
        self.post_norm = nn.LayerNorm(width, eps=1e-6)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 ``[B, cams, H, W, 3]`` -> ``[B * cams, tokens, width]``."""
        x = images_to_patches(images, self.image_size, self.patch, self.pos_embed.dtype)
        x = torch.addmm(self.pos_embed.repeat(x.shape[0], 1), x.flatten(0, 1), self.patch_embed.weight.t())
        x = (x + self.patch_embed.bias).view(-1, self.pos_embed.shape[0], self.pos_embed.shape[1])
        for blk in self.blocks:
            x = blk(x)
        return self.post_norm(x)


# --------------------------------------------------------------------------- DiT


class DiTBlock(nn.Module):
    """GR00T-style DiT block: AdaLN(t) -> self- or cross-attention -> LayerNorm -> GELU(tanh) FF.

    AdaLN here modulates the attention input only (scale, shift), as in diffusers'
    ``AdaLayerNorm``; the (shift, scale) of every step and layer are computed once per
    call from the fixed step schedule (``adaln`` holds the projection).
    """

    def __init__(self, dim: int, heads: int, head_dim: int, ff: int, ctx_dim: int | None = None):
        super().__init__()
        self.adaln = nn.Linear(dim, 2 * dim)  # silu(temb) -> (scale, shift) of the non-affine norm1
        self.cross = ctx_dim is not None
        self.heads, self.head_dim = heads, head_dim
        if self.cross:
            self.attn = CrossAttention(dim, ctx_dim, heads, head_dim, bias=True)
        else:
            self.attn = Attention(dim, heads, heads, head_dim, bias=True)
        self.norm3 = nn.LayerNorm(dim, eps=1e-5, elementwise_affine=False)
        self.ff = MLP(dim, ff)

    def forward(self, x: torch.Tensor, shift: torch.Tensor, scale1: torch.Tensor,
                ctx_kv: tuple[torch.Tensor, torch.Tensor] | None, ctx_bias: torch.Tensor | None,
                ws: Workspace | None = None) -> torch.Tensor:
        """With a workspace ``ws`` (the action stage) the residual projections run as one split-K
        kernel each (``linear_residual``)."""
        h = ada_layer_norm(x, shift, scale1, 1e-5)
        if self.cross:
            x = self.attn(h, ctx_kv, ctx_bias, x, ws)
        else:
            b, s, _ = h.shape
            q, k, v = self.attn.qkv(h).view(b, s, 3, self.heads, self.head_dim).unbind(2)
            x = linear_residual(attention(q, k.transpose(1, 2), v.transpose(1, 2), None, ws), self.attn.o, x, ws)
        return self.ff(self.norm3(x), x, ws)


# --------------------------------------------------------------------------- decoder


def fused_mlp(x: torch.Tensor, norm: RMSNorm, mlp: GatedMLP, ws: Workspace) -> torch.Tensor:
    """``x + mlp(norm(x))`` on the action stages' fused kernels (see ``DecoderLayer.forward_fused``)."""
    gu, stats = folded_norm_linear(x, norm, mlp.gate_up, ws)
    h = gated_act(gu, mlp.act, stats, norm.eps)
    return linear_residual_splitk(h, mlp.down.weight, mlp.down.bias, x, ws, stats=FOLD_NORMS)


class DecoderLayer(nn.Module):
    """Pre-norm decoder layer (Gemma / Llama / Qwen3): RMSNorm -> attention -> RMSNorm -> gated MLP."""

    def __init__(self, dim: int, heads: int, kv_heads: int, head_dim: int, mlp: int, act: str,
                 qk_norm: bool = False, eps: float = 1e-6):
        super().__init__()
        self.attn_norm = RMSNorm(dim, eps)
        self.attn = Attention(dim, heads, kv_heads, head_dim, qk_norm=qk_norm, eps=eps)
        self.mlp_norm = RMSNorm(dim, eps)
        self.mlp = GatedMLP(dim, mlp, act)

    def forward(self, x: torch.Tensor, k_out: torch.Tensor, v_out: torch.Tensor,
                rope: tuple[torch.Tensor, torch.Tensor] | None, bias: torch.Tensor | None,
                k_all: torch.Tensor | None = None, v_all: torch.Tensor | None = None,
                kv_only: bool = False, ws: Workspace | None = None) -> torch.Tensor:
        """Writes this layer's K/V of ``x`` into ``k_out``/``v_out`` and attends over
        ``k_all``/``v_all`` (a cache that contains ``k_out``), or over ``k_out`` alone.

        ``kv_only`` stops after the K/V projection: the last prefix layer of a model whose
        handoff is a KV cache needs nothing else. With a workspace ``ws`` (the action stages)
        the layer runs on the fused kernels (``forward_fused``).
        """
        if ws is not None and not kv_only:
            return self.forward_fused(x, k_out, v_out, rope, bias, k_all, v_all, ws)
        q = self.attn.project(self.attn_norm(x), k_out, v_out, rope)
        if kv_only:
            return x
        k = k_out if k_all is None else k_all
        v = v_out if v_all is None else v_all
        x = linear_residual(attention(q, k, v, bias), self.attn.o, x)
        return self.mlp(self.mlp_norm(x), x)

    def forward_fused(self, x, k_out, v_out, rope, bias, k_all, v_all, ws: Workspace) -> torch.Tensor:
        """``forward`` with the action stages' fused kernels: the attention merges its split-KV
        partials in-kernel and the o / down projections add the residual in a split-K Triton
        GEMM (one launch each, no DtoD copy, no cuBLAS reduce kernel). That GEMM also leaves its
        rows' sums of squares, so the norm after it folds into the next cuBLAS GEMM's weight and
        1 / rms into the QKV split or the gated activation (``folded_norm_linear``): no norm kernels."""
        at = self.attn
        qkv, stats = folded_norm_linear(x, self.attn_norm, at.qkv, ws)
        cos, sin = rope if rope is not None else (None, None)
        q = split_qkv(qkv, at.n_heads, at.n_kv_heads, at.head_dim, k_out, v_out, cos, sin,
                      at.q_norm.weight if at.q_norm is not None else None,
                      at.k_norm.weight if at.k_norm is not None else None, at.eps, stats, self.attn_norm.eps)
        k = k_out if k_all is None else k_all
        v = v_out if v_all is None else v_all
        x = linear_residual_splitk(attention(q, k, v, bias, ws), at.o.weight, at.o.bias, x, ws, stats=FOLD_NORMS)
        return fused_mlp(x, self.mlp_norm, self.mlp, ws)


def camera_names(n: int) -> tuple[str, ...]:
    """Default camera names: an agent/base view, a wrist view, then numbered extras."""
    return ("base", "wrist")[:n] + tuple(f"cam{i}" for i in range(2, n))
