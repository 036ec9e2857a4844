"""pi0 (Physical Intelligence): PaliGemma (SigLIP So400m + Gemma-2B) and a Gemma-300M action expert.

VLM stage: both cameras through SigLIP, projected to Gemma's width, followed by the
prompt; Gemma runs once over this bidirectional prefix and the handoff is the K/V of
all 18 layers.

Action stage: 10 Euler steps. In each, the expert's 18 layers run over the action
tokens, and at every layer their queries attend to [prefix K/V ; state ; actions]
("shared attention": the expert has its own weights but the same head layout).

Two exact rewrites keep the step loop lean:
- the state token attends only to the prefix and itself, so its K/V do not change
  between steps: it runs once, together with the first step's actions, and later
  steps process the 50 action tokens only;
- the action embedding is linear before the time MLP, so ``action_in`` is folded into
  the action half of ``time_mlp_in`` and the time half becomes a per-step bias,
  computed for the whole fixed schedule once per call.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from shared.models.base import Handoff, ModelIO, VLAModel
from shared.models.layers import (DecoderLayer, RMSNorm, SigLIP, Workspace, attn_bias, camera_names, euler_times,
                                  init_weights, rope_cos_sin, sincos_time)
from shared.models.registry import register


@dataclass(frozen=True)
class Pi0Config:
    cameras: int = 2
    image_size: int = 224  # wire size; resized on device when it differs from vit_size
    vit_size: int = 224
    patch: int = 14
    vit_width: int = 1152
    vit_depth: int = 27
    vit_heads: int = 16
    vit_mlp: int = 4304
    width: int = 2048  # Gemma-2B
    depth: int = 18  # the expert has the same depth and head layout
    heads: int = 8
    kv_heads: int = 1
    head_dim: int = 256
    mlp: int = 16384
    vocab: int = 257152
    prompt_len: int = 48
    pad_id: int = 0
    expert_width: int = 1024  # Gemma-300M
    expert_mlp: int = 4096
    state_dim: int = 32
    action_dim: int = 32
    horizon: int = 50
    steps: int = 10
    rope_theta: float = 10000.0


class Expert(nn.Module):
    def __init__(self, c: Pi0Config):
        super().__init__()
        w = c.expert_width
        self.layers = nn.ModuleList(DecoderLayer(w, c.heads, c.kv_heads, c.head_dim, c.expert_mlp, "gelu_tanh")
                                    for _ in range(c.depth))
        self.norm = RMSNorm(w)
        self.state_proj = nn.Linear(c.state_dim, w)
        self.action_in = nn.Linear(c.action_dim, w)
        self.time_mlp_in = nn.Linear(2 * w, w)  # [action_emb | time_emb] -> w
        self.time_mlp_out = nn.Linear(w, w)
        self.action_out = nn.Linear(w, c.action_dim)


@register("pi0")
class Pi0(VLAModel):
    CONFIGS = {
        "full": Pi0Config(),
        "tiny": Pi0Config(image_size=32, vit_size=32, patch=8, vit_width=32, vit_depth=2, vit_heads=2, vit_mlp=64,
                          width=64, depth=2, heads=4, kv_heads=1, head_dim=16, mlp=128, vocab=512, prompt_len=8,
                          expert_width=32, expert_mlp=64, state_dim=8, action_dim=7, horizon=5, steps=3),
    }
    ACTION_MODULES = ("expert",)

    def __init__(self, cfg: Pi0Config):
        super().__init__()
        c = self.cfg = cfg
        self.io = ModelIO(
            cameras=camera_names(c.cameras), image_shape=(c.image_size, c.image_size, 3), state_dim=c.state_dim,
            prompt_len=c.prompt_len, horizon=c.horizon, action_dim=c.action_dim, steps=c.steps)
        self.vision = SigLIP(c.vit_size, c.patch, c.vit_width, c.vit_depth, c.vit_heads, c.vit_mlp)
        self.projector = nn.Linear(c.vit_width, c.width)
        self.embed = nn.Embedding(c.vocab, c.width)
        self.layers = nn.ModuleList(DecoderLayer(c.width, c.heads, c.kv_heads, c.head_dim, c.mlp, "gelu_tanh")
                                    for _ in range(c.depth))
        self.expert = Expert(c)

    def init_weights(self, generator: torch.Generator) -> None:
        init_weights(self, generator)

    @property
    def prefix_len(self) -> int:
        c = self.cfg
        return c.cameras * (c.vit_size // c.patch) ** 2 + c.prompt_len

    def handoff_spec(self, batch: int) -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
        c, dt = self.cfg, self.embed.weight.dtype
        return {"kv": ((batch, c.depth, 2, c.kv_heads, self.prefix_len, c.head_dim), dt),
                "prefix_mask": ((batch, self.prefix_len), torch.bool),
                "state": ((batch, c.state_dim), dt)}

    def vlm_stage(self, images: torch.Tensor, state: torch.Tensor, tokens: torch.Tensor) -> Handoff:
        c = self.cfg
        b = images.shape[0]
        img = self.projector(self.vision(images)).view(b, -1, c.width)
        txt = self.embed(tokens) * math.sqrt(c.width)  # Gemma scales token embeddings
        x = torch.cat([img, txt], dim=1)
        mask = torch.cat([torch.ones(b, img.shape[1], dtype=torch.bool, device=x.device), tokens != c.pad_id], 1)
        rope = rope_cos_sin(mask.cumsum(1) - 1, c.head_dim, c.rope_theta)
        bias = attn_bias(mask[:, None, :], 1, x.dtype)  # bidirectional prefix, padding masked
        kv = x.new_empty(b, c.depth, 2, c.kv_heads, x.shape[1], c.head_dim)
        for i, layer in enumerate(self.layers):
            x = layer(x, kv[:, i, 0], kv[:, i, 1], rope, bias, kv_only=i == c.depth - 1)
        return {"kv": kv, "prefix_mask": mask, "state": state.to(x.dtype)}

    def action_stage(self, handoff: Handoff, noise: torch.Tensor) -> torch.Tensor:
        c, e = self.cfg, self.expert
        prefix_kv, mask = handoff["kv"], handoff["prefix_mask"]
        b, lp = mask.shape
        dtype, dev, w, hz = prefix_kv.dtype, prefix_kv.device, c.expert_width, c.horizon
        total = lp + 1 + hz

        # KV cache of [prefix ; state ; actions] per expert layer; the prefix part is filled once.
        kv = prefix_kv.new_empty(b, c.depth, 2, c.kv_heads, total, c.head_dim)
        kv[..., :lp, :].copy_(prefix_kv)
        valid = torch.cat([mask, torch.ones(b, 1 + hz, dtype=torch.bool, device=dev)], dim=1)
        first = valid[:, None, :].repeat(1, 1 + hz, 1)
        first[:, 0, lp + 1:] = False  # the state token does not see the actions
        groups = c.heads // c.kv_heads
        bias_first, bias = attn_bias(first, groups, dtype), attn_bias(valid[:, None, :], groups, dtype)
        pos = mask.sum(1, keepdim=True) + torch.arange(1 + hz, device=dev)
        cos, sin = rope_cos_sin(pos, c.head_dim, c.rope_theta)

        # Step-independent parts of the action/time MLP (see module docstring).
        t = euler_times(c.steps, dev)
        w_act, w_time = e.time_mlp_in.weight[:, :w], e.time_mlp_in.weight[:, w:]
        w_fold = w_act @ e.action_in.weight  # [w, action_dim]
        step_bias = F.linear(sincos_time(t, w).to(dtype), w_time, e.time_mlp_in.bias + w_act @ e.action_in.bias)
        state_tok = e.state_proj(handoff["state"].to(dtype))[:, None]

        ws = Workspace(dev)  # counters of the fused kernels' in-launch reductions
        x = noise.to(dtype)
        dt = -1.0 / c.steps
        for step in range(c.steps):
            h = F.silu(torch.addmm(step_bias[step], x.reshape(-1, c.action_dim), w_fold.t()))
            h = e.time_mlp_out(h).view(b, hz, w)
            if step == 0:
                h, off, rope, bs = torch.cat([state_tok, h], dim=1), lp, (cos, sin), bias_first
            else:
                off, rope, bs = lp + 1, (cos[:, 1:], sin[:, 1:]), bias
            s = h.shape[1]
            for i, layer in enumerate(e.layers):
                h = layer(h, kv[:, i, 0, :, off:off + s], kv[:, i, 1, :, off:off + s], rope, bs,
                          kv[:, i, 0], kv[:, i, 1], ws=ws)
            v = e.action_out(e.norm(h[:, -hz:]))
            x = torch.add(x, v, alpha=dt)
        return x.to(noise.dtype)
