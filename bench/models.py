"""A stand-in VLA with realistic stage costs for engine tests and benchmarks on the GPU
(until the model zoo lands): a compute-bound VLM (a transformer over image patches and
prompt tokens, big GEMMs) and a kernel-count-bound action stage (several small layers
times the Euler steps, attending to per-layer prefix keys/values handed over by the VLM).

Import this module to register the architecture ``heavytoy``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from shared.models.base import Handoff, ModelIO, VLAModel
from shared.models.registry import register


@dataclass(frozen=True)
class HeavyConfig:
    cameras: int = 2
    image_size: int = 224
    patch: int = 16
    width: int = 2048
    heads: int = 16
    vlm_layers: int = 18
    prompt_len: int = 48
    vocab: int = 1024
    state_dim: int = 32
    action_width: int = 1024
    action_heads: int = 8
    action_layers: int = 6
    horizon: int = 50
    action_dim: int = 32
    steps: int = 10


class Block(nn.Module):
    def __init__(self, width: int, heads: int):
        super().__init__()
        self.heads = heads
        self.n1, self.n2 = nn.LayerNorm(width), nn.LayerNorm(width)
        self.qkv = nn.Linear(width, 3 * width)
        self.proj = nn.Linear(width, width)
        self.up, self.down = nn.Linear(width, 4 * width), nn.Linear(4 * width, width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, s, d = x.shape
        q, k, v = self.qkv(self.n1(x)).view(b, s, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        x = x + self.proj(F.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(b, s, d))
        return x + self.down(F.gelu(self.up(self.n2(x))))


class CrossBlock(nn.Module):
    def __init__(self, width: int, heads: int):
        super().__init__()
        self.heads = heads
        self.n1, self.n2 = nn.LayerNorm(width), nn.LayerNorm(width)
        self.q = nn.Linear(width, width)
        self.proj = nn.Linear(width, width)
        self.up, self.down = nn.Linear(width, 2 * width), nn.Linear(2 * width, width)

    def forward(self, x: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        b, s, d = x.shape
        q = self.q(self.n1(x)).view(b, s, self.heads, d // self.heads).transpose(1, 2)
        x = x + self.proj(F.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(b, s, d))
        return x + self.down(F.silu(self.up(self.n2(x))))


@register("heavytoy")
class HeavyToyVLA(VLAModel):
    CONFIGS = {
        "full": HeavyConfig(),
        "small": HeavyConfig(image_size=32, patch=8, width=64, heads=4, vlm_layers=2, prompt_len=8, vocab=256,
                             state_dim=8, action_width=32, action_heads=2, action_layers=2, horizon=10, action_dim=7,
                             steps=3),
    }

    def __init__(self, cfg: HeavyConfig):
        super().__init__()
        self.cfg = cfg
        self.io = ModelIO(cameras=tuple(f"cam{i}" for i in range(cfg.cameras)),
                          image_shape=(cfg.image_size, cfg.image_size, 3), state_dim=cfg.state_dim,
                          prompt_len=cfg.prompt_len, horizon=cfg.horizon, action_dim=cfg.action_dim, steps=cfg.steps)
        self.patch_in = nn.Linear(3 * cfg.patch * cfg.patch, cfg.width)
        self.embed = nn.Embedding(cfg.vocab, cfg.width)
        self.state_in = nn.Linear(cfg.state_dim, cfg.width)
        self.blocks = nn.ModuleList(Block(cfg.width, cfg.heads) for _ in range(cfg.vlm_layers))
        self.kv = nn.ModuleList(nn.Linear(cfg.width, 2 * cfg.action_width) for _ in range(cfg.action_layers))
        self.act_in = nn.Linear(cfg.action_dim, cfg.action_width)
        self.time_in = nn.Linear(1, cfg.action_width)
        self.act_blocks = nn.ModuleList(CrossBlock(cfg.action_width, cfg.action_heads) for _ in range(cfg.action_layers))
        self.act_out = nn.Linear(cfg.action_width, cfg.action_dim)

    def vlm_stage(self, images: torch.Tensor, state: torch.Tensor, tokens: torch.Tensor) -> Handoff:
        c = self.cfg
        b, n = images.shape[:2]
        p = c.patch
        g = c.image_size // p
        x = images.to(self.patch_in.weight.dtype).div(127.5).sub(1.0)
        x = x.view(b, n, g, p, g, p, 3).permute(0, 1, 2, 4, 3, 5, 6).reshape(b, n * g * g, p * p * 3)
        seq = torch.cat([self.patch_in(x), self.embed(tokens % c.vocab), self.state_in(state.to(x.dtype))[:, None]], dim=1)
        for blk in self.blocks:
            seq = blk(seq)
        out = {}
        hd = c.action_width // c.action_heads
        for i, proj in enumerate(self.kv):
            k, v = proj(seq).view(b, -1, 2, c.action_heads, hd).permute(2, 0, 3, 1, 4)
            out[f"k{i}"], out[f"v{i}"] = k, v
        return out

    def action_stage(self, handoff: Handoff, noise: torch.Tensor) -> torch.Tensor:
        c = self.cfg
        x = noise.to(self.act_in.weight.dtype)
        dt = -1.0 / c.steps
        for s in range(c.steps):
            t = torch.full((1, 1, 1), 1.0 + s * dt, dtype=x.dtype, device=x.device)
            h = self.act_in(x) + self.time_in(t)
            for i, blk in enumerate(self.act_blocks):
                h = blk(h, handoff[f"k{i}"], handoff[f"v{i}"])
            x = x + dt * self.act_out(h)
        return x
