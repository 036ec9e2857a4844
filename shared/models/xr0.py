"""Xiaomi-Robotics-0 (XR0): a Qwen3-VL-4B VLM and a 16-layer AdaLN DiT that reads the VLM's KV cache.

VLM stage: each 256x256 camera through the Qwen3-VL ViT (patch 16, 2-D RoPE, 24 layers),
2x2 patch merging to 64 tokens of width 2560, with DeepStack: the features of ViT
layers 5, 11 and 17 go through their own mergers and are added to the image-token
hidden states after LM layers 0, 1 and 2. [images ; prompt] run through the 36 causal
LM layers; the handoff is the KV cache of the last 16 layers (DiT layer i reads VLM
layer 20 + i), the prefix padding mask and the robot state.

Action stage: 5 Euler steps over [sink ; state ; 30 action tokens]. Each DiT layer
attends jointly over [VLM KV ; its own K/V] with QK-RMSNorm; action tokens see the
prefix, the sink and state tokens and the actions in a causal window of 4. AdaLN
(shift, scale, gate for attention and MLP) comes from one time MLP plus a learned
per-layer table; for the fixed schedule all of it is computed once per call.

Simplifications (same op sizes): text positions use 1-D RoPE instead of M-RoPE; the
action encoder's shape is not published (the pi0-style action/time MLP is assumed,
which lands the head at the published 0.28 B).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from shared.models import fused
from shared.models.base import Handoff, ModelIO, VLAModel
from shared.models.layers import (MLP, Attention, DecoderLayer, GatedMLP, ViTBlock, ada_layer_norm, attention,
                                  attn_bias, camera_names, gated_act, images_to_patches, init_weights,
                                  rope_cos_sin, rope_cos_sin_2d, sincos_time, timestep_embedding)
from shared.models.registry import register


@dataclass(frozen=True)
class XR0Config:
    cameras: int = 2
    image_size: int = 256  # wire size
    vit_size: int = 256  # -> 16 x 16 patches -> 64 merged tokens per camera (unverified)
    patch: int = 16
    temporal_patch: int = 2  # a still image is repeated over the temporal patch
    vit_width: int = 1024
    vit_depth: int = 24
    vit_heads: int = 16
    vit_mlp: int = 4096
    vit_pos_grid: int = 48  # learned 48 x 48 position table, interpolated to the patch grid
    merge: int = 2
    deepstack: tuple[int, ...] = (5, 11, 17)
    width: int = 2560
    depth: int = 36
    heads: int = 32
    kv_heads: int = 8
    head_dim: int = 128
    mlp: int = 9728
    vocab: int = 151936
    prompt_len: int = 48  # unverified
    # Qwen's <|endoftext|>, its tokenizer's pad token. Its id 0 is "!": a prompt mask of `tokens != 0` would drop
    # every "!" of a real prompt. (The byte-level fallback's ids stay below 258.)
    pad_id: int = 151643
    rope_theta: float = 5000000.0
    dit_layers: int = 16  # DiT layer i reads VLM layer depth - dit_layers + i
    dit_width: int = 1024
    dit_heads: int = 8
    dit_kv_heads: int = 8
    dit_mlp: int = 4096
    window: int = 4  # causal window among action tokens
    time_freqs: int = 256
    state_dim: int = 32
    action_dim: int = 32
    horizon: int = 30
    steps: int = 5


class Merger(nn.Module):
    """2x2 patch merge -> LayerNorm -> MLP to the LM width (``post_norm``: norm after the merge, DeepStack)."""

    def __init__(self, c: XR0Config, post_norm: bool):
        super().__init__()
        self.merge, self.post_norm = c.merge, post_norm
        merged = c.vit_width * c.merge ** 2
        self.norm = nn.LayerNorm(merged if post_norm else c.vit_width, eps=1e-6)
        self.mlp = MLP(merged, merged, c.width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.post_norm:
            x = self.norm(x)
        n, p, d = x.shape
        g, r = math.isqrt(p), self.merge
        x = x.view(n, g // r, r, g // r, r, d).transpose(2, 3).reshape(n, p // r ** 2, d * r * r)
        if self.post_norm:
            x = self.norm(x)
        return self.mlp(x)


class VisionTower(nn.Module):
    def __init__(self, c: XR0Config):
        super().__init__()
        self.c = c
        self.patch_embed = nn.Linear(c.temporal_patch * c.patch ** 2 * 3, c.vit_width)
        self.pos_embed = nn.Parameter(torch.zeros(c.vit_pos_grid ** 2, c.vit_width))
        self.blocks = nn.ModuleList(ViTBlock(c.vit_width, c.vit_heads, c.vit_mlp) for _ in range(c.vit_depth))
        self.merger = Merger(c, post_norm=False)
        self.deepstack = nn.ModuleList(Merger(c, post_norm=True) for _ in c.deepstack)

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """uint8 [B, cams, H, W, 3] -> merged tokens [B * cams, T, width] and the DeepStack features."""
        c = self.c
        g = c.vit_size // c.patch
        x = images_to_patches(images, c.vit_size, c.patch, self.pos_embed.dtype)
        x = self.patch_embed(x.repeat(1, 1, c.temporal_patch))
        x = x + fused.resize_table(self.pos_embed, c.vit_pos_grid, g)
        idx = torch.arange(g, device=x.device)
        rope = rope_cos_sin_2d(idx.repeat_interleave(g)[None], idx.repeat(g)[None], c.vit_width // c.vit_heads)
        taps = []
        for i, blk in enumerate(self.blocks):
            x = blk(x, rope)
            if i in c.deepstack:
                taps.append(self.deepstack[c.deepstack.index(i)](x))
        return self.merger(x), taps


class DiTLayer(nn.Module):
    """AdaLN (shift, scale, gate) -> joint attention with QK-norm -> AdaLN -> SwiGLU, gated residuals."""

    def __init__(self, c: XR0Config):
        super().__init__()
        w = c.dit_width
        self.table = nn.Parameter(torch.zeros(6, w))  # added to the shared time modulation
        self.attn = Attention(w, c.dit_heads, c.dit_kv_heads, w // c.dit_heads, qk_norm=True)
        self.mlp = GatedMLP(w, c.dit_mlp, "silu")

    def forward(self, x: torch.Tensor, mod: torch.Tensor, k_out: torch.Tensor, v_out: torch.Tensor,
                rope: tuple[torch.Tensor, torch.Tensor], bias: torch.Tensor, k_all: torch.Tensor,
                v_all: torch.Tensor) -> torch.Tensor:
        """``mod`` [6, w]: shift1, 1 + scale1, gate1, shift2, 1 + scale2, gate2 of this layer and step."""
        h = ada_layer_norm(x, mod[0], mod[1])
        q = self.attn.project(h, k_out, v_out, rope)
        x = torch.addcmul(x, mod[2], self.attn.o(attention(q, k_all, v_all, bias)))
        h = ada_layer_norm(x, mod[3], mod[4])
        return torch.addcmul(x, mod[5], self.mlp.down(gated_act(self.mlp.gate_up(h), "silu")))


class DiT(nn.Module):
    def __init__(self, c: XR0Config):
        super().__init__()
        w = c.dit_width
        self.time_in = nn.Linear(c.time_freqs, w)
        self.time_out = nn.Linear(w, 6 * w)
        self.sink = nn.Parameter(torch.zeros(1, w))
        self.state_proj = nn.Linear(c.state_dim, w)
        self.action_in = nn.Linear(c.action_dim, w)
        self.action_time_in = nn.Linear(2 * w, w)  # [action_emb | time_emb] -> w
        self.action_time_out = nn.Linear(w, w)
        self.layers = nn.ModuleList(DiTLayer(c) for _ in range(c.dit_layers))
        self.final_table = nn.Parameter(torch.zeros(2, w))
        self.action_out = nn.Linear(w, c.action_dim)


@register("xr0")
class XR0(VLAModel):
    CONFIGS = {
        "full": XR0Config(),
        "tiny": XR0Config(image_size=32, vit_size=32, patch=4, vit_width=32, vit_depth=4, vit_heads=2, vit_mlp=64,
                          vit_pos_grid=6, deepstack=(0, 1, 2), width=64, depth=6, heads=4, kv_heads=2, head_dim=16,
                          mlp=128, vocab=512, prompt_len=8, pad_id=0, dit_layers=3, dit_width=32, dit_heads=2,
                          dit_kv_heads=2, dit_mlp=64, time_freqs=16, state_dim=8, action_dim=7, horizon=6, steps=3),
    }
    ACTION_MODULES = ("dit",)

    def __init__(self, cfg: XR0Config):
        super().__init__()
        c = self.cfg = cfg
        assert c.dit_width // c.dit_heads * c.dit_kv_heads == c.head_dim * c.kv_heads, "DiT reads the VLM KV"
        self.io = ModelIO(cameras=camera_names(c.cameras), image_shape=(c.image_size, c.image_size, 3),
                          state_dim=c.state_dim, prompt_len=c.prompt_len, horizon=c.horizon,
                          action_dim=c.action_dim, steps=c.steps)
        self.vision = VisionTower(c)
        self.embed = nn.Embedding(c.vocab, c.width)
        self.layers = nn.ModuleList(DecoderLayer(c.width, c.heads, c.kv_heads, c.head_dim, c.mlp, "silu", qk_norm=True)
                                    for _ in range(c.depth))
        self.dit = DiT(c)

    def init_weights(self, generator: torch.Generator) -> None:
        init_weights(self, generator)

    @property
    def prefix_len(self) -> int:
        c = self.cfg
        return c.cameras * (c.vit_size // c.patch // c.merge) ** 2 + c.prompt_len

    def handoff_spec(self, batch: int) -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
        c, dt = self.cfg, self.embed.weight.dtype
        return {"kv": ((batch, c.dit_layers, 2, c.kv_heads, self.prefix_len, c.head_dim), dt),
                "prefix_mask": ((batch, self.prefix_len), torch.bool),
                "state": ((batch, c.state_dim), dt)}

    def vlm_stage(self, images: torch.Tensor, state: torch.Tensor, tokens: torch.Tensor) -> Handoff:
        c = self.cfg
        b = images.shape[0]
        img, taps = self.vision(images)
        n_img = c.cameras * img.shape[1]
        x = torch.cat([img.view(b, n_img, c.width), self.embed(tokens)], dim=1)
        n, dev = x.shape[1], x.device
        mask = torch.cat([torch.ones(b, n_img, dtype=torch.bool, device=dev), tokens != c.pad_id], dim=1)
        allowed = torch.ones(n, n, dtype=torch.bool, device=dev).tril() & mask[:, None, :]
        bias = attn_bias(allowed, c.heads // c.kv_heads, x.dtype)
        rope = rope_cos_sin(mask.cumsum(1) - 1, c.head_dim, c.rope_theta)
        first = c.depth - c.dit_layers
        kv = x.new_empty(b, c.dit_layers, 2, c.kv_heads, n, c.head_dim)
        scratch = self.layers[0].attn.new_kv(x)
        for i, layer in enumerate(self.layers):
            k, v = (kv[:, i - first, 0], kv[:, i - first, 1]) if i >= first else scratch
            x = layer(x, k, v, rope, bias, kv_only=i == c.depth - 1)
            if i < len(taps):  # DeepStack: inject ViT features into the image tokens
                x[:, :n_img] += taps[i].view(b, n_img, c.width)
        return {"kv": kv, "prefix_mask": mask, "state": state.to(x.dtype)}

    def action_stage(self, handoff: Handoff, noise: torch.Tensor) -> torch.Tensor:
        c, d = self.cfg, self.dit
        prefix_kv, mask = handoff["kv"], handoff["prefix_mask"]
        b, lp = mask.shape
        dtype, dev, w, hz = prefix_kv.dtype, prefix_kv.device, c.dit_width, c.horizon
        s = 2 + hz  # sink, state, actions
        hd = w // c.dit_heads

        kv = prefix_kv.new_empty(b, c.dit_layers, 2, c.dit_kv_heads, lp + s, hd)
        kv[..., :lp, :].copy_(prefix_kv)
        i = torch.arange(s, device=dev)
        qa, ka = (i - 2)[:, None], (i - 2)[None, :]
        own = torch.where((qa >= 0) & (ka >= 0), (ka <= qa) & (ka > qa - c.window), ka < 0)
        allowed = torch.cat([mask[:, None, :].expand(b, s, lp), own.expand(b, s, s)], dim=2)
        bias = attn_bias(allowed, c.dit_heads // c.dit_kv_heads, dtype)
        rope = rope_cos_sin(mask.sum(1, keepdim=True) + i, hd, c.rope_theta)

        # Once per call: time MLP and every layer's modulation for the fixed schedule.
        t = 1.0 - torch.arange(c.steps, device=dev, dtype=torch.float32) / c.steps
        t_hidden = F.silu(d.time_in(timestep_embedding(t * 1000, c.time_freqs).to(dtype)))
        t_mod = d.time_out(t_hidden).view(c.steps, 6, w)
        t_mod[:, 1] += 1  # the modulation is 1 + scale
        t_mod[:, 4] += 1
        mods = [t_mod + layer.table for layer in d.layers]  # [steps, 6, w] each
        final = d.final_table[None] + t_hidden[:, None]
        final[:, 1] += 1
        w_act, w_time = d.action_time_in.weight[:, :w], d.action_time_in.weight[:, w:]
        w_fold = w_act @ d.action_in.weight
        step_bias = F.linear(sincos_time(t, w).to(dtype), w_time, d.action_time_in.bias + w_act @ d.action_in.bias)
        head_tokens = torch.cat([d.sink[None].expand(b, 1, w), d.state_proj(handoff["state"].to(dtype))[:, None]], 1)

        x = noise.to(dtype)
        dt = -1.0 / c.steps
        for step in range(c.steps):
            a = F.silu(torch.addmm(step_bias[step], x.reshape(-1, c.action_dim), w_fold.t()))
            h = torch.cat([head_tokens, d.action_time_out(a).view(b, hz, w)], dim=1)
            for j, layer in enumerate(d.layers):
                h = layer(h, mods[j][step], kv[:, j, 0, :, lp:], kv[:, j, 1, :, lp:], rope, bias,
                          kv[:, j, 0], kv[:, j, 1])
            v = d.action_out(ada_layer_norm(h[:, 2:], final[step, 0], final[step, 1]))
            x = torch.add(x, v, alpha=dt)
        return x.to(noise.dtype)
