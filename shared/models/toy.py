"""A small two-stage VLA for fast CPU tests: a patch encoder and MLP 'VLM' producing a
handoff, and a flow-matching action head with a few Euler steps."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from shared.models.base import Handoff, ModelIO, VLAModel
from shared.models.registry import register


@dataclass(frozen=True)
class ToyConfig:
    cameras: int = 2
    image_size: int = 64  # wire resolution; the stage pools to 16x16 patches of 4x4
    width: int = 64
    state_dim: int = 8
    prompt_len: int = 16
    vocab: int = 256
    horizon: int = 10
    action_dim: int = 7
    steps: int = 4


@register("toy")
class ToyVLA(VLAModel):
    CONFIGS = {"tiny": ToyConfig(), "full": ToyConfig(width=256, image_size=224)}

    def __init__(self, cfg: ToyConfig):
        super().__init__()
        self.cfg = cfg
        self.io = ModelIO(
            cameras=tuple(f"cam{i}" for i in range(cfg.cameras)),
            image_shape=(cfg.image_size, cfg.image_size, 3),
            state_dim=cfg.state_dim, prompt_len=cfg.prompt_len,
            horizon=cfg.horizon, action_dim=cfg.action_dim, steps=cfg.steps,
        )
        self.patch = nn.Linear(3 * 16, cfg.width)
        self.embed = nn.Embedding(cfg.vocab, cfg.width)
        self.state_in = nn.Linear(cfg.state_dim, cfg.width)
        self.vlm_mlp = nn.Sequential(nn.Linear(cfg.width, 4 * cfg.width), nn.GELU(), nn.Linear(4 * cfg.width, cfg.width))
        self.act_in = nn.Linear(cfg.action_dim, cfg.width)
        self.time_in = nn.Linear(cfg.width, cfg.width)
        self.act_mlp = nn.Sequential(nn.Linear(2 * cfg.width, 4 * cfg.width), nn.SiLU(), nn.Linear(4 * cfg.width, cfg.width))
        self.act_out = nn.Linear(cfg.width, cfg.action_dim)

    def vlm_stage(self, images: torch.Tensor, state: torch.Tensor, tokens: torch.Tensor) -> Handoff:
        b, n = images.shape[:2]
        x = images.to(self.patch.weight.dtype).div(127.5).sub(1.0).flatten(0, 1).permute(0, 3, 1, 2)
        x = F.adaptive_avg_pool2d(x, 16)  # [b*n, 3, 16, 16]
        x = x.unfold(2, 4, 4).unfold(3, 4, 4).permute(0, 2, 3, 1, 4, 5).reshape(b, n * 16, 48)
        seq = torch.cat([self.patch(x), self.embed(tokens), self.state_in(state.to(x.dtype))[:, None]], dim=1)
        seq = seq + self.vlm_mlp(seq)
        return {"context": seq.mean(dim=1)}

    def action_stage(self, handoff: Handoff, noise: torch.Tensor) -> torch.Tensor:
        ctx = handoff["context"]
        x = noise.to(ctx.dtype)
        dt = -1.0 / self.cfg.steps
        half = self.cfg.width // 2
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=x.device, dtype=torch.float32) / half)
        for i in range(self.cfg.steps):
            t = 1.0 + i * dt
            temb = self.time_in(torch.cat([torch.sin(t * freqs), torch.cos(t * freqs)]).to(x.dtype))
            h = self.act_in(x) + temb
            h = self.act_mlp(torch.cat([h, ctx[:, None].expand_as(h)], dim=-1))
            x = x + dt * self.act_out(h)
        return x
