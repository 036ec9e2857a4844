"""Running a model's two stages on a batch of requests.

The CPU path runs the stages eagerly. The GPU path (CUDA graphs per stage and batch size,
static handoff buffers, SM levels) plugs in behind the same methods, so engines never
care which one they drive.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np
import torch

from services.executor.scheduler import Request
from shared.models.base import Handoff, InterfaceError, VLAModel


class EagerStages:
    """Both stages of one model, run eagerly on its device."""

    def __init__(self, model: VLAModel, device: torch.device, seed: int = 0):
        self.model = model
        self.device = device
        self.io = model.io
        self._noise_gen = torch.Generator().manual_seed(seed)

    def inputs(self, batch: list[Request]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Stack a batch's observations (and noise) into device tensors."""
        images = torch.from_numpy(np.stack([r.images for r in batch]))
        state = torch.from_numpy(np.stack([r.state for r in batch]))
        tokens = torch.from_numpy(np.stack([r.tokens for r in batch]))
        noise = torch.stack([
            torch.from_numpy(r.noise) if r.noise is not None
            else torch.randn(self.io.horizon, self.io.action_dim, generator=self._noise_gen)
            for r in batch
        ])
        dev = self.device
        return (images.to(dev, non_blocking=True), state.to(dev, non_blocking=True),
                tokens.to(dev, non_blocking=True), noise.to(dev, non_blocking=True))

    @torch.inference_mode()
    def vlm(self, images: torch.Tensor, state: torch.Tensor, tokens: torch.Tensor) -> Handoff:
        return self.model.vlm_stage(images, state, tokens)

    @torch.inference_mode()
    def action(self, handoff: Handoff, noise: torch.Tensor) -> torch.Tensor:
        return self.model.action_stage(handoff, noise)


# ----------------------------------------------------------------------------- static buffers


def _copy_exact(dst: torch.Tensor, src: torch.Tensor, what: str) -> None:
    """``dst.copy_(src)`` without broadcasting: a stage output one row short filled a whole batch with one robot's
    actions. Python runs it only while capturing or running eagerly, never at a graph's replay."""
    if src.shape != dst.shape:
        raise InterfaceError(f"{what}: the stage returned shape {list(src.shape)}, its buffer is {list(dst.shape)}")
    dst.copy_(src)


NOISE = "__noise__"  # the batch's initial noise rides along with the handoff
TensorSpec = tuple[tuple[int, ...], torch.dtype]


def _align(n: int, a: int = 256) -> int:
    return (n + a - 1) // a * a


@dataclass
class Pack:
    """Named tensors laid out in one flat byte buffer, so moving all of them is one copy."""

    flat: torch.Tensor  # uint8
    views: dict[str, torch.Tensor]

    @classmethod
    def allocate(cls, specs: dict[str, TensorSpec], device: torch.device, pin: bool = False) -> "Pack":
        offsets: dict[str, tuple[int, int]] = {}
        total = 0
        for name, (shape, dtype) in specs.items():
            nbytes = math.prod(shape) * dtype.itemsize
            offsets[name] = (total, nbytes)
            total = _align(total + nbytes)
        flat = torch.zeros(max(total, 1), dtype=torch.uint8, device=device, pin_memory=pin)
        views = {name: flat[o:o + n].view(specs[name][1]).view(specs[name][0]) for name, (o, n) in offsets.items()}
        return cls(flat, views)


def profile_key(model: VLAModel) -> str:
    """What the SM table is keyed by: architecture and size, never the model's name, so
    fine-tuned variants (same shapes, other weights) share profiled entries."""
    cfg = getattr(model, "cfg", None)
    for size, known in getattr(type(model), "CONFIGS", {}).items():
        if cfg is not None and cfg == known:
            return f"{model.arch}:{size}"
    shapes = repr([(n, tuple(p.shape), str(p.dtype)) for n, p in model.named_parameters()]) + repr(model.io)
    return f"{model.arch or type(model).__name__}:{hashlib.sha1(shapes.encode()).hexdigest()[:8]}"


class BufferedStages:
    """One model's stages over static buffers per batch size, run eagerly.

    Data path of a batch: host staging (pinned) -> device inputs -> VLM -> ``vlm_out``
    (handoff + noise) -> one copy -> ``act_in`` -> action -> ``dev_out`` -> pinned host
    output (two slots, so a result can be read while the next action stage runs). The
    lockstep engine drives these steps on its streams; ``GraphStages`` replays CUDA graphs
    of the VLM and action steps over the same buffers. On the CPU this class *is* the
    engine's backend, which is what lets the lockstep logic be tested without a GPU.
    """

    def __init__(self, model: VLAModel, device: torch.device, batch_sizes: list[int], seed: int = 0):
        self.model = model
        self.device = device
        self.io = model.io
        self.arch = profile_key(model)
        self.batch_sizes = list(batch_sizes)
        self._noise_gen = torch.Generator().manual_seed(seed)
        self._cuda = device.type == "cuda"
        # Two pinned staging buffers per batch size: one may still feed an in-flight upload
        # while the other is filled (prestaging the likely next batch during a lockstep).
        self.host_in: dict[int, list[Pack]] = {}
        self.host_np: dict[int, list[dict[str, np.ndarray]]] = {}
        self._cur: dict[int, int] = {}
        self._prestaged: dict[int, list[Request] | None] = {}
        self.prestage_hits = self.prestage_misses = 0
        self.dev_in: dict[int, Pack] = {}
        self.vlm_out: dict[int, Pack] = {}
        self.act_in: dict[int, Pack] = {}
        self.dev_out: dict[int, torch.Tensor] = {}
        self.host_out: dict[int, list[torch.Tensor]] = {}

    def input_specs(self, b: int) -> dict[str, TensorSpec]:
        io = self.io
        return {"images": ((b, len(io.cameras), *io.image_shape), torch.uint8),
                "state": ((b, io.state_dim), torch.float32),
                "tokens": ((b, io.prompt_len), torch.int64),
                NOISE: ((b, io.horizon, io.action_dim), torch.float32)}

    @torch.no_grad()
    def allocate(self) -> None:
        """Allocate every buffer; one eager VLM pass per batch size reveals the handoff's layout."""
        for b in self.batch_sizes:
            specs = self.input_specs(b)
            self.host_in[b] = [Pack.allocate(specs, torch.device("cpu"), pin=self._cuda) for _ in range(2)]
            self.host_np[b] = [{k: v.numpy() for k, v in p.views.items()} for p in self.host_in[b]]
            self._cur[b], self._prestaged[b] = 0, None
            self.dev_in[b] = Pack.allocate(specs, self.device)
            images, state, tokens = self.model.example_inputs(b, self.device, torch.Generator().manual_seed(b))
            handoff = self.model.vlm_stage(images, state, tokens)
            if NOISE in handoff:
                raise ValueError(f"handoff key {NOISE!r} is reserved")
            hspecs = {k: (tuple(v.shape), v.dtype) for k, v in handoff.items()} | {NOISE: specs[NOISE]}
            self.vlm_out[b] = Pack.allocate(hspecs, self.device)
            self.act_in[b] = Pack.allocate(hspecs, self.device)
            out_shape = (b, self.io.horizon, self.io.action_dim)
            self.dev_out[b] = torch.zeros(out_shape, dtype=torch.float32, device=self.device)
            self.host_out[b] = [torch.zeros(out_shape, dtype=torch.float32, pin_memory=self._cuda) for _ in range(2)]
            # Valid data everywhere, so a profiling lockstep never computes on garbage (NaN paths can be slower).
            self.dev_in[b].views["images"].copy_(images)
            self.dev_in[b].views["state"].copy_(state)
            self.dev_in[b].views["tokens"].copy_(tokens)
            self.dev_in[b].views[NOISE].copy_(self.model.noise(b, self.device, torch.Generator().manual_seed(b)))
            self._vlm_body(b)
            self.handoff(b)

    def stage(self, b: int, batch: list[Request]) -> None:
        """Host side: put a batch's observations (and noise) into a pinned staging buffer.

        When ``prestage`` already copied exactly these requests, only the noise is written:
        the image copies then happened while the GPU was busy, not between locksteps.
        """
        spare = 1 - self._cur[b]
        pre, self._prestaged[b] = self._prestaged[b], None
        hit = pre is not None and len(pre) == len(batch) and all(x is y for x, y in zip(pre, batch))
        if hit:
            self.prestage_hits += 1
        else:
            self.prestage_misses += 1
            self._copy_observations(self.host_np[b][spare], batch)
        noise = self.host_in[b][spare].views[NOISE]
        for i, r in enumerate(batch):
            if r.noise is None:  # engines that do not draw noise at submission
                torch.randn(self.io.horizon, self.io.action_dim, generator=self._noise_gen, out=noise[i])
            elif not hit:
                self.host_np[b][spare][NOISE][i] = r.noise
        self._cur[b] = spare

    def prestage(self, b: int, batch: list[Request]) -> None:
        """Copy the observations (and fixed noise) of the batch likely admitted next into the
        idle staging buffer."""
        np_in = self.host_np[b][1 - self._cur[b]]
        self._copy_observations(np_in, batch)
        for i, r in enumerate(batch):
            if r.noise is not None:
                np_in[NOISE][i] = r.noise
        self._prestaged[b] = list(batch)  # references, not ids: a freed request's id can be reused

    @staticmethod
    def _copy_observations(np_in: dict[str, np.ndarray], batch: list[Request]) -> None:
        for i, r in enumerate(batch):
            np_in["images"][i] = r.images
            np_in["state"][i] = r.state
            np_in["tokens"][i] = r.tokens

    def capture_vlm(self, b: int, levels: set) -> None:
        """Eager stages have no graphs; an eager VLM is restricted by the stream it runs on."""

    def drop_vlm(self, keep: dict) -> None:
        pass

    # The methods below enqueue work on the current stream (on the CPU they just run).

    def vlm(self, b: int, level: int | None = None) -> None:
        self.upload(b)
        self._vlm_body(b)

    def upload(self, b: int) -> None:
        self.dev_in[b].flat.copy_(self.host_in[b][self._cur[b]].flat, non_blocking=True)

    def handoff(self, b: int) -> None:
        self.act_in[b].flat.copy_(self.vlm_out[b].flat, non_blocking=True)

    def action(self, b: int, slot: int) -> None:
        self._action_body(b)
        self.host_out[b][slot].copy_(self.dev_out[b], non_blocking=True)

    def result(self, b: int, slot: int) -> np.ndarray:
        """The action chunks of the batch whose action stage wrote ``slot`` (a view; copy it)."""
        return self.host_out[b][slot].numpy()

    @torch.no_grad()
    def _vlm_body(self, b: int) -> None:
        # no_grad rather than inference_mode: the static buffers are ordinary tensors that
        # every thread may write in place.
        v = self.dev_in[b].views
        out = self.vlm_out[b].views
        handoff = self.model.vlm_stage(v["images"], v["state"], v["tokens"])
        for k, t in handoff.items():
            _copy_exact(out[k], t, f"handoff[{k!r}]")
        out[NOISE].copy_(v[NOISE])

    @torch.no_grad()
    def _action_body(self, b: int) -> None:
        v = self.act_in[b].views
        actions = self.model.action_stage({k: t for k, t in v.items() if k != NOISE}, v[NOISE])
        _copy_exact(self.dev_out[b], actions, "actions")

    def eager_reference(self, images: torch.Tensor, state: torch.Tensor, tokens: torch.Tensor,
                        noise: torch.Tensor) -> torch.Tensor:
        """Both stages run plainly on the model, for checking the engine's replies."""
        with torch.inference_mode():
            return self.model.action_stage(self.model.vlm_stage(images, state, tokens), noise).float()
