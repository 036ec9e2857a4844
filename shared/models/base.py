"""The two-stage interface every served VLA model follows.

A VLA model is split into the two stages the engine schedules separately:

- ``vlm_stage(images, state, tokens) -> handoff``: the compute-heavy vision-language
  model. ``images`` is uint8 ``[B, cameras, H, W, 3]`` exactly as robots send them;
  resizing and normalisation happen inside, on the model's device.
- ``action_stage(handoff, noise) -> actions``: the action expert / diffusion
  transformer with its Euler flow-matching steps inside; ``noise`` and the result
  are ``[B, horizon, action_dim]``.

Both stages have static shapes for a given batch size, never synchronise with the
host and never branch on data, so the engine can capture each as a CUDA graph and
pass the handoff through static buffers.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

Handoff = dict[str, torch.Tensor]


@dataclass(frozen=True)
class ModelIO:
    """What a model takes from a robot and gives back."""

    cameras: tuple[str, ...]
    image_shape: tuple[int, int, int]  # H, W, 3 of each uint8 camera image on the wire
    state_dim: int
    prompt_len: int  # tokens after padding / truncation
    horizon: int
    action_dim: int
    steps: int  # Euler flow-matching steps in the action stage


class VLAModel(nn.Module):
    """Base class of every two-stage VLA model in the zoo."""

    arch: str = ""  # registry name of the architecture, e.g. "pi0"
    io: ModelIO
    # Names of the top-level child modules whose parameters belong to the action stage;
    # every other parameter counts to the VLM stage (see stage_parameters()).
    ACTION_MODULES: tuple[str, ...] = ()

    def init_weights(self, generator: torch.Generator) -> None:
        """Seeded random init, called by ``build_model`` after the model was materialised on
        its device. The default re-runs each submodule's ``reset_parameters`` under the seed
        held by ``generator``; zoo models override it with a generator-driven init."""
        device = generator.device
        devices = [device.index if device.index is not None else torch.cuda.current_device()] \
            if device.type == "cuda" else []
        with torch.random.fork_rng(devices=devices):
            torch.manual_seed(generator.initial_seed())
            for m in self.modules():
                if hasattr(m, "reset_parameters"):
                    m.reset_parameters()

    def stage_parameters(self) -> dict[str, int]:
        """Parameter counts per stage: ``{"vlm_params": n, "action_params": n}``.

        Works on a model built on the meta device (no memory)."""
        counts = {"vlm_params": 0, "action_params": 0}
        for name, p in self.named_parameters():
            key = "action_params" if name.split(".", 1)[0] in self.ACTION_MODULES else "vlm_params"
            counts[key] += p.numel()
        return counts

    def handoff_spec(self, batch: int) -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
        """Shape and dtype of every handoff tensor at a batch size, so an engine can allocate
        static buffers before running anything. Batch is dim 0 of every handoff tensor.

        The default runs the VLM stage once on example inputs; zoo models answer
        analytically (no compute)."""
        with torch.no_grad():
            out = self.vlm_stage(*self.example_inputs(batch))
        return {k: (tuple(v.shape), v.dtype) for k, v in out.items()}

    def vlm_stage(self, images: torch.Tensor, state: torch.Tensor, tokens: torch.Tensor) -> Handoff:
        raise NotImplementedError(f"{type(self).__name__} does not implement vlm_stage")

    def action_stage(self, handoff: Handoff, noise: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError(f"{type(self).__name__} does not implement action_stage")

    def example_inputs(self, batch: int, device: torch.device | str | None = None,
                       generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Random, correctly shaped stage inputs (images, state, tokens) for tests and benchmarks."""
        device = torch.device(device) if device is not None else next(self.parameters()).device
        io = self.io
        images = torch.randint(0, 256, (batch, len(io.cameras), *io.image_shape), dtype=torch.uint8,
                               generator=generator).to(device)
        state = torch.randn(batch, io.state_dim, generator=generator).to(device)
        # Below the model's vocabulary where its config states one: a user's model with a smaller vocabulary failed
        # its first handoff_spec (an IndexError in its embedding) and so stopped the executor's start.
        vocab = getattr(getattr(self, "cfg", None), "vocab", 200)
        tokens = torch.randint(1, max(2, min(200, vocab)), (batch, io.prompt_len), generator=generator).to(device)
        return images, state, tokens

    def noise(self, batch: int, device: torch.device | str | None = None,
              generator: torch.Generator | None = None) -> torch.Tensor:
        device = torch.device(device) if device is not None else next(self.parameters()).device
        return torch.randn(batch, self.io.horizon, self.io.action_dim, generator=generator).to(device)


class InterfaceError(ValueError):
    """A model that does not follow the two-stage interface: its ``io``, or what its stages return."""


def _check_io(io: ModelIO) -> list[str]:
    problems = []
    if not isinstance(io, ModelIO):
        return [f"io is a {type(io).__name__}, not a ModelIO"]
    cams = io.cameras
    if (not isinstance(cams, (tuple, list)) or not cams or not all(isinstance(c, str) and c for c in cams)
            or len(set(cams)) != len(cams)):
        problems.append(f"io.cameras: expected a tuple of one or more distinct camera names, got {cams!r}")
    shape = io.image_shape
    if (not isinstance(shape, (tuple, list)) or len(shape) != 3 or shape[2] != 3
            or not all(isinstance(d, int) and d >= 1 for d in shape)):
        problems.append(f"io.image_shape: expected (H, W, 3) of positive ints (robots send RGB), got {shape!r}")
    for field in ("state_dim", "prompt_len", "horizon", "action_dim", "steps"):
        value = getattr(io, field)
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            problems.append(f"io.{field}: expected a positive int, got {value!r}")
    return problems


def is_device_fault(exc: BaseException) -> bool:
    """Out of device memory, or an error of the device itself: not the model's fault, and maybe gone after a restart
    (memory a crashed process still held), so not a reason to refuse the model for good."""
    return isinstance(exc, torch.OutOfMemoryError) or (
        isinstance(exc, RuntimeError) and ("CUDA" in str(exc) or type(exc).__name__ == "AcceleratorError"))


def _run(name: str, what: str, batch: int, call):
    """``call()``, with whatever it raises as an InterfaceError naming the stage: a model that fails its check is
    refused with one line (exit 2), not a traceback and exit 1, which asks a supervisor to start it again. A device
    fault (is_device_fault) is raised as it is."""
    try:
        return call()
    except InterfaceError:
        raise
    except Exception as exc:
        if is_device_fault(exc):
            raise
        raise InterfaceError(f"{name}.{what} failed at batch {batch}: {type(exc).__name__}: {exc}") from exc


def check_interface(model: VLAModel, batches: tuple[int, ...] = (1, 2)) -> None:
    """Raise InterfaceError unless ``model`` follows the two-stage interface at each batch size: a valid ``io``, a
    handoff of tensors with the batch as dim 0 and the shapes and dtypes ``handoff_spec`` promised (engines allocate
    their static buffers from it), and actions of exactly ``[B, horizon, action_dim]`` in a floating dtype.

    Run once per model before an engine serves it. Engines copy outputs into static buffers, where a wrong shape
    broadcasts: actions of the wrong size, or one robot's actions in every row of its batch, went out as replies."""
    name = type(model).__name__
    problems = _check_io(getattr(model, "io", None))
    if problems:
        raise InterfaceError(f"{name}: " + "; ".join(problems))
    io = model.io
    device = next(model.parameters()).device
    with torch.inference_mode():
        for b in batches:
            handoff = _run(name, "vlm_stage", b, lambda: model.vlm_stage(*model.example_inputs(b, device)))
            if not isinstance(handoff, dict) or not handoff or not all(
                    isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in handoff.items()):
                raise InterfaceError(f"{name}.vlm_stage: expected a dict of named tensors, got "
                                     f"{type(handoff).__name__}")
            got = {k: (tuple(v.shape), v.dtype) for k, v in handoff.items()}
            for k, (shape, _) in got.items():
                if not shape or shape[0] != b:
                    raise InterfaceError(f"{name}.vlm_stage: handoff[{k!r}] has shape {list(shape)} at batch {b}; "
                                         "dim 0 must be the batch")
            spec = _run(name, "handoff_spec", b, lambda: model.handoff_spec(b))
            if not isinstance(spec, dict):
                raise InterfaceError(f"{name}.handoff_spec: expected {{name: (shape, dtype)}}, got {type(spec).__name__}")
            spec = _run(name, "handoff_spec", b, lambda: {k: (tuple(s), d) for k, (s, d) in spec.items()})
            if got != spec:
                raise InterfaceError(f"{name}: at batch {b} vlm_stage returned {got}, but handoff_spec says {spec}")
            actions = _run(name, "action_stage", b, lambda: model.action_stage(handoff, model.noise(b, device)))
            want = (b, io.horizon, io.action_dim)
            if not isinstance(actions, torch.Tensor) or tuple(actions.shape) != want:
                got_shape = list(actions.shape) if isinstance(actions, torch.Tensor) else type(actions).__name__
                raise InterfaceError(f"{name}.action_stage: expected actions of shape {list(want)} "
                                     f"[batch, horizon, action_dim] at batch {b}, got {got_shape}")
            if not actions.is_floating_point():
                raise InterfaceError(f"{name}.action_stage: expected floating-point actions, got {actions.dtype}")
