"""SmolVLA (Hugging Face LeRobot): SmolVLM-2 (SigLIP-B/16 + SmolLM2-360M, first 16 layers) and a
720-wide action expert that interleaves joint attention and cross-attention.

VLM stage: each 512x512 camera through SigLIP, pixel-shuffled 4x4 (1024 -> 64 tokens),
then [images ; prompt ; state token] through 16 Llama-style layers. Images and prompt
attend bidirectionally, the state token sees everything before it. The handoff is the
post-RoPE K/V of the 16 layers.

Action stage: 10 Euler steps over 50 action tokens. Even expert layers attend jointly
over [prefix K/V of the same VLM layer ; actions] (causal among actions); odd layers
cross-attend to the prefix only, through the expert's own k/v projections (320 -> 320)
applied to the cached VLM K/V. Those re-projections do not depend on the step, so they
run once per call, as does the time half of the action/time MLP (see pi0.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from shared.models import layers
from shared.models.base import Handoff, ModelIO, VLAModel
from shared.models.fused import Workspace, linear_residual_splitk, split_qkv
from shared.models.layers import (DecoderLayer, GatedMLP, RMSNorm, SigLIP, attention, attn_bias, camera_names,
                                  euler_times, folded_norm_linear, fused_mlp, init_weights, linear_residual,
                                  rope_cos_sin, sincos_time)
from shared.models.registry import register


@dataclass(frozen=True)
class SmolVLAConfig:
    cameras: int = 2
    image_size: int = 512  # wire size
    vit_size: int = 512
    patch: int = 16
    vit_width: int = 768
    vit_depth: int = 12
    vit_heads: int = 12
    vit_mlp: int = 3072
    shuffle: int = 4  # pixel shuffle factor: (512/16)^2 = 1024 patches -> 64 tokens
    width: int = 960  # SmolLM2-360M
    depth: int = 16  # VLM layers used (of 32); the expert has as many
    heads: int = 15
    kv_heads: int = 5
    head_dim: int = 64
    mlp: int = 2560
    vocab: int = 49280
    prompt_len: int = 48
    pad_id: int = 0
    expert_width: int = 720
    expert_mlp: int = 2048
    state_dim: int = 32
    action_dim: int = 32
    horizon: int = 50
    steps: int = 10
    rope_theta: float = 100000.0


class CrossLayer(nn.Module):
    """Expert layer that attends to the prefix only, re-projecting the cached VLM K/V."""

    def __init__(self, c: SmolVLAConfig):
        super().__init__()
        w, kv = c.expert_width, c.kv_heads * c.head_dim
        self.heads, self.head_dim = c.heads, c.head_dim
        self.attn_norm = RMSNorm(w)
        self.q = nn.Linear(w, c.heads * c.head_dim, bias=False)
        self.k_proj = nn.Linear(kv, kv, bias=False)
        self.v_proj = nn.Linear(kv, kv, bias=False)
        self.o = nn.Linear(c.heads * c.head_dim, w, bias=False)
        self.mlp_norm = RMSNorm(w)
        self.mlp = GatedMLP(w, c.expert_mlp, "silu")

    def context_kv(self, k: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[B, n_kv, L, D] cached VLM K/V -> the expert's K/V for this layer (same shape)."""
        def proj(lin: nn.Linear, t: torch.Tensor) -> torch.Tensor:
            b, h, length, d = t.shape
            return lin(t.transpose(1, 2).reshape(b, length, h * d)).view(b, length, h, d).transpose(1, 2).contiguous()
        return proj(self.k_proj, k), proj(self.v_proj, v)

    def forward(self, x: torch.Tensor, ctx: tuple[torch.Tensor, torch.Tensor],
                rope: tuple[torch.Tensor, torch.Tensor], bias: torch.Tensor, ws: Workspace | None = None) -> torch.Tensor:
        if ws is not None:  # the fused kernels and the norms folded away (DecoderLayer.forward_fused)
            qp, stats = folded_norm_linear(x, self.attn_norm, self.q, ws)
            q = split_qkv(qp, self.heads, 0, self.head_dim, None, None, *rope, row_stats=stats,
                          row_eps=self.attn_norm.eps)
            x = linear_residual_splitk(attention(q, ctx[0], ctx[1], bias, ws), self.o.weight, self.o.bias, x, ws,
                                       stats=layers.FOLD_NORMS)
            return fused_mlp(x, self.mlp_norm, self.mlp, ws)
        q = split_qkv(self.q(self.attn_norm(x)), self.heads, 0, self.head_dim, None, None, *rope)
        x = linear_residual(attention(q, ctx[0], ctx[1], bias), self.o, x)
        return self.mlp(self.mlp_norm(x), x)


class Expert(nn.Module):
    def __init__(self, c: SmolVLAConfig):
        super().__init__()
        w = c.expert_width
        self.layers = nn.ModuleList(
            DecoderLayer(w, c.heads, c.kv_heads, c.head_dim, c.expert_mlp, "silu") if i % 2 == 0 else CrossLayer(c)
            for i in range(c.depth))
        self.norm = RMSNorm(w)
        self.action_in = nn.Linear(c.action_dim, w)
        self.time_mlp_in = nn.Linear(2 * w, w)
        self.time_mlp_out = nn.Linear(w, w)
        self.action_out = nn.Linear(w, c.action_dim)


@register("smolvla")
class SmolVLA(VLAModel):
    CONFIGS = {
        "full": SmolVLAConfig(),
        "tiny": SmolVLAConfig(image_size=32, vit_size=32, patch=4, vit_width=32, vit_depth=2, vit_heads=2,
                              vit_mlp=64, shuffle=2, width=48, depth=4, heads=6, kv_heads=2, head_dim=8, mlp=96,
                              vocab=512, prompt_len=8, expert_width=36, expert_mlp=64, state_dim=8, action_dim=7,
                              horizon=5, steps=3),
    }
    ACTION_MODULES = ("expert",)

    def __init__(self, cfg: SmolVLAConfig):
        super().__init__()
        c = self.cfg = cfg
        self.io = ModelIO(cameras=camera_names(c.cameras), image_shape=(c.image_size, c.image_size, 3),
                          state_dim=c.state_dim, prompt_len=c.prompt_len, horizon=c.horizon,
                          action_dim=c.action_dim, steps=c.steps)
        self.vision = SigLIP(c.vit_size, c.patch, c.vit_width, c.vit_depth, c.vit_heads, c.vit_mlp)
        self.connector = nn.Linear(c.vit_width * c.shuffle ** 2, c.width, bias=False)
        self.embed = nn.Embedding(c.vocab, c.width)
        self.state_proj = nn.Linear(c.state_dim, c.width)
        self.layers = nn.ModuleList(DecoderLayer(c.width, c.heads, c.kv_heads, c.head_dim, c.mlp, "silu")
                                    for _ in range(c.depth))
        self.expert = Expert(c)

    def init_weights(self, generator: torch.Generator) -> None:
        init_weights(self, generator)

    @property
    def image_tokens(self) -> int:
        c = self.cfg
        return (c.vit_size // c.patch // c.shuffle) ** 2

    @property
    def prefix_len(self) -> int:
        return self.cfg.cameras * self.image_tokens + self.cfg.prompt_len + 1

    def handoff_spec(self, batch: int) -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
        c = self.cfg
        return {"kv": ((batch, c.depth, 2, c.kv_heads, self.prefix_len, c.head_dim), self.embed.weight.dtype),
                "prefix_mask": ((batch, self.prefix_len), torch.bool)}

    def pixel_shuffle(self, x: torch.Tensor) -> torch.Tensor:
        """[N, g*g, d] -> [N, (g/r)^2, d*r*r]: each r x r block of patches becomes one token."""
        n, p, d = x.shape
        g, r = math.isqrt(p), self.cfg.shuffle
        x = x.view(n, g // r, r, g // r, r, d).transpose(2, 3)
        return x.reshape(n, (g // r) ** 2, r * r * d)

    def vlm_stage(self, images: torch.Tensor, state: torch.Tensor, tokens: torch.Tensor) -> Handoff:
        c = self.cfg
        b = images.shape[0]
        scale = math.sqrt(c.width)  # SmolVLA scales image and text embeddings alike
        img = self.connector(self.pixel_shuffle(self.vision(images))).view(b, -1, c.width) * scale
        txt = self.embed(tokens) * scale
        st = self.state_proj(state.to(txt.dtype))[:, None]
        x = torch.cat([img, txt, st], dim=1)
        dev, n = x.device, x.shape[1]
        mask = torch.cat([torch.ones(b, img.shape[1], dtype=torch.bool, device=dev), tokens != c.pad_id,
                          torch.ones(b, 1, dtype=torch.bool, device=dev)], dim=1)
        allowed = mask[:, None, :].repeat(1, n, 1)
        allowed[:, :-1, -1] = False  # images and prompt do not see the state token
        bias = attn_bias(allowed, c.heads // c.kv_heads, x.dtype)
        rope = rope_cos_sin(mask.cumsum(1) - 1, c.head_dim, c.rope_theta)
        kv = x.new_empty(b, c.depth, 2, c.kv_heads, n, c.head_dim)
        for i, layer in enumerate(self.layers):
            x = layer(x, kv[:, i, 0], kv[:, i, 1], rope, bias, kv_only=i == c.depth - 1)
        return {"kv": kv, "prefix_mask": mask}

    def action_stage(self, handoff: Handoff, noise: torch.Tensor) -> torch.Tensor:
        c, e = self.cfg, self.expert
        prefix_kv, mask = handoff["kv"], handoff["prefix_mask"]
        b, lp = mask.shape
        dtype, dev, w, hz = prefix_kv.dtype, prefix_kv.device, c.expert_width, c.horizon
        groups = c.heads // c.kv_heads

        # Joint layers: cache [prefix ; actions], prefix copied once. Cross layers: K/V re-projected once.
        kv = prefix_kv.new_empty(b, c.depth // 2, 2, c.kv_heads, lp + hz, c.head_dim)
        kv[..., :lp, :].copy_(prefix_kv[:, 0::2])
        ctx = [e.layers[i].context_kv(prefix_kv[:, i, 0], prefix_kv[:, i, 1]) for i in range(1, c.depth, 2)]
        causal = torch.ones(hz, hz, dtype=torch.bool, device=dev).tril()
        joint = torch.cat([mask[:, None, :].expand(b, hz, lp), causal.expand(b, hz, hz)], dim=2)
        bias_joint, bias_cross = attn_bias(joint, groups, dtype), attn_bias(mask[:, None, :], groups, dtype)
        rope = rope_cos_sin(mask.sum(1, keepdim=True) + torch.arange(hz, device=dev), c.head_dim, c.rope_theta)

        t = euler_times(c.steps, dev)
        w_act, w_time = e.time_mlp_in.weight[:, :w], e.time_mlp_in.weight[:, w:]
        w_fold = w_act @ e.action_in.weight
        step_bias = F.linear(sincos_time(t, w).to(dtype), w_time, e.time_mlp_in.bias + w_act @ e.action_in.bias)

        ws = Workspace(dev)
        x = noise.to(dtype)
        dt = -1.0 / c.steps
        for step in range(c.steps):
            h = F.silu(torch.addmm(step_bias[step], x.reshape(-1, c.action_dim), w_fold.t()))
            h = e.time_mlp_out(h).view(b, hz, w)
            for i, layer in enumerate(e.layers):
                if i % 2 == 0:
                    j = i // 2
                    h = layer(h, kv[:, j, 0, :, lp:], kv[:, j, 1, :, lp:], rope, bias_joint, kv[:, j, 0], kv[:, j, 1],
                              ws=ws)
                else:
                    h = layer(h, ctx[i // 2], rope, bias_cross, ws=ws)
            x = torch.add(x, e.action_out(e.norm(h)), alpha=dt)
        return x.to(noise.dtype)
