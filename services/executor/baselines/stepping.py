"""One denoising step at a time, with the rows of a batch at *different* steps.

The process-disaggregated engine (the vLLM-Omni design) merges newly arrived requests
into a running action batch at every denoising step, so a batch holds requests at
different points of their flow-matching schedule. The zoo models only expose the whole
action stage (``action_stage``: per-call set-up, then a loop over steps with the step
index shared by the batch), so this module adds the missing per-step form from the
outside, without editing the model files (another engineer optimises those):

- ``init_rows(handoff, noise)``: what a request needs before its first step (its
  KV cache, masks, RoPE, conditioning tokens; the model's per-call set-up, per request);
- ``step(S, n)``: one Euler step of rows ``[:n]`` of the running state ``S``; each row
  reads its own step index from ``S["step"]`` (per-row time embedding, per-row AdaLN
  modulation) and the step increments it;
- ``S["x"]`` holds the actions being integrated (the model's dtype).

Everything step-independent and request-independent (the folded time-MLP weights, the
schedule's time embeddings and modulations) is computed once from the weights. Each
adapter reproduces its model's ``action_stage`` arithmetic exactly (same modules, same
rewrites; for pi0 the state token is recomputed at every step instead of cached after the
first, which gives identical values); ``tests/test_baselines.py`` checks every adapter
against ``action_stage`` with rows admitted at different steps. If a model's action stage
changes, that test fails until its adapter follows.

Static shapes for a given ``n`` and no host synchronisation, so ``step(S, n)`` can be
captured as a CUDA graph per running-batch size.
"""

from __future__ import annotations

import importlib
import math

import torch
import torch.nn.functional as F

from shared.models.base import Handoff, VLAModel
from shared.models.layers import (attention, attn_bias, euler_times, linear_residual, rope_cos_sin, sincos_time,
                                  timestep_embedding)

State = dict[str, torch.Tensor]

ADAPTERS: dict[str, type["StepAdapter"]] = {}


def _adapter(arch: str):
    def deco(cls):
        ADAPTERS[arch] = cls
        return cls
    return deco


def step_adapter(model: VLAModel) -> "StepAdapter | None":
    """The per-step form of ``model``'s action stage, or None when its architecture has none."""
    cls = ADAPTERS.get(model.arch)
    return cls(model) if cls is not None else None


def _rows_buffer(t: torch.Tensor, capacity: int) -> torch.Tensor:
    """A ``[capacity, *t.shape[1:]]`` buffer like ``t``; padded storage (attention biases) stays padded."""
    if t.dim() >= 2 and t.stride(-2) > t.shape[-1] and t.is_contiguous() is False:
        store = torch.zeros(capacity, *t.shape[1:-1], t.stride(-2), dtype=t.dtype, device=t.device)
        return store[..., :t.shape[-1]]
    return torch.zeros(capacity, *t.shape[1:], dtype=t.dtype, device=t.device)


def _ada_rows(x: torch.Tensor, shift: torch.Tensor, scale_plus_one: torch.Tensor, eps: float) -> torch.Tensor:
    """AdaLN with a per-row modulation ``[n, w]`` (the models' fused form takes one vector per batch)."""
    return torch.addcmul(shift[:, None], F.layer_norm(x, (x.shape[-1],), None, None, eps), scale_plus_one[:, None])


class StepAdapter:
    steps: int

    def __init__(self, model: VLAModel):
        self.model = model
        self.steps = model.io.steps
        self.horizon, self.action_dim = model.io.horizon, model.io.action_dim
        self.dtype = next(model.parameters()).dtype
        with torch.no_grad():
            self._prepare()

    def _prepare(self) -> None:
        """Step-independent, request-independent tensors (from the weights only)."""

    def init_rows(self, handoff: Handoff, noise: torch.Tensor) -> State:
        raise NotImplementedError

    def step(self, S: State, n: int) -> None:
        raise NotImplementedError

    # ------------------------------------------------------------------ generic parts

    @torch.no_grad()
    def allocate(self, handoff1: Handoff, noise1: torch.Tensor, capacity: int) -> State:
        """Running-state buffers for ``capacity`` rows, shaped from a one-request example."""
        rows = self.init_rows(handoff1, noise1)
        S = {k: _rows_buffer(v, capacity) for k, v in rows.items()}
        S["step"] = torch.zeros(capacity, dtype=torch.int64, device=noise1.device)
        return S

    @torch.no_grad()
    def admit(self, S: State, at: int, handoff: Handoff, noise: torch.Tensor) -> None:
        """Write the initial state of ``len(noise)`` requests into rows ``[at, at + b)``."""
        b = noise.shape[0]
        for k, v in self.init_rows(handoff, noise).items():
            S[k][at:at + b].copy_(v)
        S["step"][at:at + b].zero_()

    @staticmethod
    def view(S: State, n: int) -> State:
        return {k: v[:n] for k, v in S.items()}

    @staticmethod
    def move(S: State, src: torch.Tensor, dst: torch.Tensor) -> None:
        """Copy rows ``src`` to rows ``dst`` (compaction after requests leave)."""
        for v in S.values():
            v[dst] = v[src]

    @torch.no_grad()
    def run(self, S: State, n: int) -> None:
        self.step(self.view(S, n), n)

    def actions(self, S: State, rows: torch.Tensor) -> torch.Tensor:
        return S["x"][rows].float()

    # helpers
    def _gather(self, table: torch.Tensor, S: State, repeat: int = 1) -> torch.Tensor:
        """``table[step of each row]``, each row's entry repeated ``repeat`` times (per token)."""
        out = table[S["step"]]
        return out.repeat_interleave(repeat, 0) if repeat > 1 else out


@_adapter("toy")
class ToyAdapter(StepAdapter):
    def _prepare(self) -> None:
        m = self.model
        c = m.cfg
        dt = -1.0 / c.steps
        half = c.width // 2
        dev = m.time_in.weight.device
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=dev, dtype=torch.float32) / half)
        temb = []
        for i in range(c.steps):
            t = 1.0 + i * dt
            temb.append(m.time_in(torch.cat([torch.sin(t * freqs), torch.cos(t * freqs)]).to(self.dtype)))
        self.temb = torch.stack(temb)  # [steps, width]
        self.dt = dt

    def init_rows(self, handoff: Handoff, noise: torch.Tensor) -> State:
        ctx = handoff["context"]
        return {"ctx": ctx.clone(), "x": noise.to(ctx.dtype)}

    def step(self, S: State, n: int) -> None:
        m, x, ctx = self.model, S["x"], S["ctx"]
        h = m.act_in(x) + self._gather(self.temb, S)[:, None]
        h = m.act_mlp(torch.cat([h, ctx[:, None].expand_as(h)], dim=-1))
        x.copy_(x + self.dt * m.act_out(h))
        S["step"].add_(1)


class _FoldedTime(StepAdapter):
    """pi0 / SmolVLA: ``action_in`` folded into the action half of ``time_mlp_in``; the time half is a per-step bias."""

    def _prepare(self) -> None:
        c, e, w = self.model.cfg, self.model.expert, self.model.cfg.expert_width
        t = euler_times(c.steps, e.time_mlp_in.weight.device)
        w_act, w_time = e.time_mlp_in.weight[:, :w], e.time_mlp_in.weight[:, w:]
        self.w_fold_t = (w_act @ e.action_in.weight).t().contiguous()
        self.step_bias = F.linear(sincos_time(t, w).to(self.dtype), w_time,
                                  e.time_mlp_in.bias + w_act @ e.action_in.bias)
        self.dt = -1.0 / c.steps

    def _time_mlp(self, e, S: State, n: int, w: int) -> torch.Tensor:
        x = S["x"]
        h = F.silu(torch.addmm(self._gather(self.step_bias, S, self.horizon), x.reshape(-1, self.action_dim),
                               self.w_fold_t))
        return e.time_mlp_out(h).view(n, self.horizon, w)


@_adapter("pi0")
class Pi0Adapter(_FoldedTime):
    def init_rows(self, handoff: Handoff, noise: torch.Tensor) -> State:
        c, e = self.model.cfg, self.model.expert
        prefix_kv, mask = handoff["kv"], handoff["prefix_mask"]
        b, lp = mask.shape
        dev, hz = prefix_kv.device, c.horizon
        total = lp + 1 + hz
        kv = prefix_kv.new_zeros(b, c.depth, 2, c.kv_heads, total, c.head_dim)
        kv[..., :lp, :].copy_(prefix_kv)
        valid = torch.cat([mask, torch.ones(b, 1 + hz, dtype=torch.bool, device=dev)], dim=1)
        first = valid[:, None, :].repeat(1, 1 + hz, 1)
        first[:, 0, lp + 1:] = False  # the state token does not see the actions
        pos = mask.sum(1, keepdim=True) + torch.arange(1 + hz, device=dev)
        cos, sin = rope_cos_sin(pos, c.head_dim, c.rope_theta)
        return {"kv": kv, "bias": attn_bias(first, c.heads // c.kv_heads, kv.dtype), "cos": cos, "sin": sin,
                "state_tok": e.state_proj(handoff["state"].to(kv.dtype))[:, None], "x": noise.to(kv.dtype)}

    def step(self, S: State, n: int) -> None:
        # Every step runs [state ; actions] with the first step's mask: the state token's K/V
        # depend only on the prefix and the state, so recomputing them gives the cached values,
        # and the action rows attend to exactly what the model's later steps attend to.
        c, e = self.model.cfg, self.model.expert
        kv, x = S["kv"], S["x"]
        lp = kv.shape[-2] - 1 - c.horizon
        h = torch.cat([S["state_tok"], self._time_mlp(e, S, n, c.expert_width)], dim=1)
        s = h.shape[1]
        for i, layer in enumerate(e.layers):
            h = layer(h, kv[:, i, 0, :, lp:lp + s], kv[:, i, 1, :, lp:lp + s], (S["cos"], S["sin"]), S["bias"],
                      kv[:, i, 0], kv[:, i, 1])
        v = e.action_out(e.norm(h[:, -c.horizon:]))
        x.copy_(torch.add(x, v, alpha=self.dt))
        S["step"].add_(1)


@_adapter("smolvla")
class SmolVLAAdapter(_FoldedTime):
    def init_rows(self, handoff: Handoff, noise: torch.Tensor) -> State:
        c, e = self.model.cfg, self.model.expert
        prefix_kv, mask = handoff["kv"], handoff["prefix_mask"]
        b, lp = mask.shape
        dev, hz, dtype = prefix_kv.device, c.horizon, prefix_kv.dtype
        groups = c.heads // c.kv_heads
        kv = prefix_kv.new_zeros(b, c.depth // 2, 2, c.kv_heads, lp + hz, c.head_dim)
        kv[..., :lp, :].copy_(prefix_kv[:, 0::2])
        out: State = {"kv": kv}
        for i in range(1, c.depth, 2):
            out[f"ctx_k{i}"], out[f"ctx_v{i}"] = e.layers[i].context_kv(prefix_kv[:, i, 0], prefix_kv[:, i, 1])
        causal = torch.ones(hz, hz, dtype=torch.bool, device=dev).tril()
        joint = torch.cat([mask[:, None, :].expand(b, hz, lp), causal.expand(b, hz, hz)], dim=2)
        out["bias_joint"], out["bias_cross"] = attn_bias(joint, groups, dtype), attn_bias(mask[:, None, :], groups, dtype)
        out["cos"], out["sin"] = rope_cos_sin(mask.sum(1, keepdim=True) + torch.arange(hz, device=dev), c.head_dim,
                                              c.rope_theta)
        out["x"] = noise.to(dtype)
        return out

    def step(self, S: State, n: int) -> None:
        c, e = self.model.cfg, self.model.expert
        kv, x, rope = S["kv"], S["x"], (S["cos"], S["sin"])
        lp = kv.shape[-2] - c.horizon
        h = self._time_mlp(e, S, n, c.expert_width)
        for i, layer in enumerate(e.layers):
            if i % 2 == 0:
                j = i // 2
                h = layer(h, kv[:, j, 0, :, lp:], kv[:, j, 1, :, lp:], rope, S["bias_joint"], kv[:, j, 0], kv[:, j, 1])
            else:
                h = layer(h, (S[f"ctx_k{i}"], S[f"ctx_v{i}"]), rope, S["bias_cross"])
        x.copy_(torch.add(x, e.action_out(e.norm(h)), alpha=self.dt))
        S["step"].add_(1)


@_adapter("xr0")
class XR0Adapter(StepAdapter):
    def _prepare(self) -> None:
        m = self.model
        c, d = m.cfg, m.dit
        w, dtype, dev = c.dit_width, self.dtype, d.time_in.weight.device
        xr0 = importlib.import_module(type(m).__module__)
        self._gated_act = xr0.gated_act
        t = 1.0 - torch.arange(c.steps, device=dev, dtype=torch.float32) / c.steps
        t_hidden = F.silu(d.time_in(timestep_embedding(t * 1000, c.time_freqs).to(dtype)))
        t_mod = d.time_out(t_hidden).view(c.steps, 6, w)
        t_mod[:, 1] += 1
        t_mod[:, 4] += 1
        self.mods = [t_mod + layer.table for layer in d.layers]  # [steps, 6, w]
        final = d.final_table[None] + t_hidden[:, None]
        final[:, 1] += 1
        self.final = final  # [steps, 2, w]
        w_act, w_time = d.action_time_in.weight[:, :w], d.action_time_in.weight[:, w:]
        self.w_fold_t = (w_act @ d.action_in.weight).t().contiguous()
        self.step_bias = F.linear(sincos_time(t, w).to(dtype), w_time, d.action_time_in.bias + w_act @ d.action_in.bias)
        self.dt = -1.0 / c.steps

    def init_rows(self, handoff: Handoff, noise: torch.Tensor) -> State:
        c, d = self.model.cfg, self.model.dit
        prefix_kv, mask = handoff["kv"], handoff["prefix_mask"]
        b, lp = mask.shape
        dtype, dev, w, hz = prefix_kv.dtype, prefix_kv.device, c.dit_width, c.horizon
        s = 2 + hz
        hd = w // c.dit_heads
        kv = prefix_kv.new_zeros(b, c.dit_layers, 2, c.dit_kv_heads, lp + s, hd)
        kv[..., :lp, :].copy_(prefix_kv)
        i = torch.arange(s, device=dev)
        qa, ka = (i - 2)[:, None], (i - 2)[None, :]
        own = torch.where((qa >= 0) & (ka >= 0), (ka <= qa) & (ka > qa - c.window), ka < 0)
        allowed = torch.cat([mask[:, None, :].expand(b, s, lp), own.expand(b, s, s)], dim=2)
        cos, sin = rope_cos_sin(mask.sum(1, keepdim=True) + i, hd, c.rope_theta)
        head = torch.cat([d.sink[None].expand(b, 1, w), d.state_proj(handoff["state"].to(dtype))[:, None]], 1)
        return {"kv": kv, "bias": attn_bias(allowed, c.dit_heads // c.dit_kv_heads, dtype), "cos": cos, "sin": sin,
                "head": head, "x": noise.to(dtype)}

    def step(self, S: State, n: int) -> None:
        c, d = self.model.cfg, self.model.dit
        kv, x, rope, bias = S["kv"], S["x"], (S["cos"], S["sin"]), S["bias"]
        hz, w = c.horizon, c.dit_width
        lp = kv.shape[-2] - 2 - hz
        a = F.silu(torch.addmm(self._gather(self.step_bias, S, hz), x.reshape(-1, c.action_dim), self.w_fold_t))
        h = torch.cat([S["head"], d.action_time_out(a).view(n, hz, w)], dim=1)
        for j, layer in enumerate(d.layers):
            mod = self._gather(self.mods[j], S)  # [n, 6, w]
            g = _ada_rows(h, mod[:, 0], mod[:, 1], 1e-6)
            q = layer.attn.project(g, kv[:, j, 0, :, lp:], kv[:, j, 1, :, lp:], rope)
            h = torch.addcmul(h, mod[:, 2, None], layer.attn.o(attention(q, kv[:, j, 0], kv[:, j, 1], bias)))
            g = _ada_rows(h, mod[:, 3], mod[:, 4], 1e-6)
            h = torch.addcmul(h, mod[:, 5, None], layer.mlp.down(self._gated_act(layer.mlp.gate_up(g), "silu")))
        fin = self._gather(self.final, S)
        v = d.action_out(_ada_rows(h[:, 2:], fin[:, 0], fin[:, 1], 1e-6))
        x.copy_(torch.add(x, v, alpha=self.dt))
        S["step"].add_(1)


@_adapter("groot_n15")
class GR00TAdapter(StepAdapter):
    def _prepare(self) -> None:
        m = self.model
        c, hd = m.cfg, m.head
        e, w, dtype, dev = c.embodiment_id, c.dit_width, self.dtype, hd.dit.time_in.weight.device
        t = torch.arange(c.steps, device=dev, dtype=torch.float32) / c.steps
        t_disc = torch.floor(t * 1000)
        temb = hd.dit.time_out(F.silu(hd.dit.time_in(timestep_embedding(t_disc, c.time_freqs).to(dtype))))
        temb_act = F.silu(temb)
        self.ada = []
        for blk in hd.dit.blocks:
            scale, shift = blk.adaln(temb_act).chunk(2, dim=-1)
            self.ada.append((1 + scale, shift))
        shift_out, scale_out = hd.dit.proj_out_1(temb_act).chunk(2, dim=-1)
        self.shift_out, self.scale_out = shift_out, 1 + scale_out
        enc = hd.action_encoder
        w2a, w2t = enc.w2.weight[e, :w], enc.w2.weight[e, w:]
        self.w_fold = enc.w1.weight[e] @ w2a
        self.step_bias = torch.addmm(enc.w2.bias[e] + enc.w1.bias[e] @ w2a, timestep_embedding(t_disc, w).to(dtype), w2t)
        self.pos_bias = enc.w3.bias[e] + hd.pos_embed.weight[:c.horizon]  # [hz, w], tiled per row
        self.dt = 1.0 / c.steps

    def init_rows(self, handoff: Handoff, noise: torch.Tensor) -> State:
        c, hd = self.model.cfg, self.model.head
        vl, mask = handoff["vl"], handoff["vl_mask"]
        b, dtype = vl.shape[0], vl.dtype
        vl = hd.vlln(vl)
        for blk in hd.adapter:
            vl = blk(vl)
        out: State = {}
        for i, blk in enumerate(hd.dit.blocks):
            if blk.cross:
                out[f"ctx_k{i}"], out[f"ctx_v{i}"] = blk.attn.context_kv(vl)
        out["ctx_bias"] = attn_bias(mask[:, None, :], 1, dtype)
        out["head"] = torch.cat([hd.state_encoder(handoff["state"].to(dtype), c.embodiment_id)[:, None],
                                 hd.future_tokens.weight[None].expand(b, -1, -1)], dim=1)
        out["x"] = noise.to(dtype)
        return out

    def step(self, S: State, n: int) -> None:
        c, hd = self.model.cfg, self.model.head
        e, w, hz = c.embodiment_id, c.dit_width, c.horizon
        enc, x = hd.action_encoder, S["x"]
        a = F.silu(torch.addmm(self._gather(self.step_bias, S, hz), x.reshape(-1, c.action_dim), self.w_fold))
        a = torch.addmm(self.pos_bias.repeat(n, 1), a, enc.w3.weight[e]).view(n, hz, w)
        h = torch.cat([S["head"], a], dim=1)
        for i, blk in enumerate(hd.dit.blocks):
            scale1, shift = self._gather(self.ada[i][0], S), self._gather(self.ada[i][1], S)
            g = _ada_rows(h, shift, scale1, 1e-5)
            if blk.cross:
                h = blk.attn(g, (S[f"ctx_k{i}"], S[f"ctx_v{i}"]), S["ctx_bias"], h)
            else:
                b_, s_, _ = g.shape
                q, k, v = blk.attn.qkv(g).view(b_, s_, 3, blk.heads, blk.head_dim).unbind(2)
                h = linear_residual(attention(q, k.transpose(1, 2), v.transpose(1, 2)), blk.attn.o, h)
            h = blk.ff(blk.norm3(h), h)
        g = _ada_rows(h[:, -hz:], self._gather(self.shift_out, S), self._gather(self.scale_out, S), 1e-6)
        v = hd.action_decoder(hd.dit.proj_out_2(g), e)
        x.copy_(torch.add(x, v, alpha=self.dt))
        S["step"].add_(1)
