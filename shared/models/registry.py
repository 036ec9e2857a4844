"""Registry of two-stage VLA architectures, so users can serve their own."""

from __future__ import annotations

import importlib
import os

import torch

from shared.models.base import VLAModel

_ARCHS: dict[str, type[VLAModel]] = {}


def register(name: str):
    """Class decorator: ``@register("my_vla")`` makes an architecture servable by name.

    The class needs a ``CONFIGS`` dict mapping size names ("full", "tiny", ...) to its
    config dataclass and a constructor taking that config.
    """

    def wrap(cls: type[VLAModel]) -> type[VLAModel]:
        if name in _ARCHS and _ARCHS[name] is not cls:
            raise ValueError(f"architecture {name!r} is already registered")
        cls.arch = name
        _ARCHS[name] = cls
        return cls

    return wrap


def architectures() -> dict[str, type[VLAModel]]:
    _load_builtin()
    return dict(_ARCHS)


def get_architecture(name: str) -> type[VLAModel]:
    _load_builtin()
    if name not in _ARCHS:
        raise KeyError(f"unknown architecture {name!r}; known: {', '.join(sorted(_ARCHS))}")
    return _ARCHS[name]


def build_model(arch: str, size: str = "tiny", seed: int = 0, device: str | torch.device = "cpu",
                dtype: torch.dtype | None = None) -> VLAModel:
    """Build an architecture at a named size with seeded random weights (same seed, same weights)."""
    cls = get_architecture(arch)
    configs = getattr(cls, "CONFIGS", {})
    if size not in configs:
        raise KeyError(f"{arch} has no size {size!r}; sizes: {', '.join(sorted(configs))}")
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    if dtype is None:
        dtype = torch.bfloat16 if device.type == "cuda" else torch.float32
    # Build on the meta device and materialise straight in the target dtype on the target
    # device: a 4.7 B-parameter model never exists as fp32 on the host.
    with torch.device("meta"):
        model = cls(configs[size])
    model = model.to(dtype=dtype).to_empty(device=device)
    model.init_weights(torch.Generator(device).manual_seed(seed))
    return model.eval().requires_grad_(False)


def build_meta(arch: str, size: str = "full") -> VLAModel:
    """The architecture on the meta device: shapes and parameter counts, no memory."""
    cls = get_architecture(arch)
    with torch.device("meta"):
        return cls(cls.CONFIGS[size])


def _load_builtin() -> None:
    # Importing the architecture modules runs their @register decorators.
    import shared.models.groot_n15  # noqa: F401
    import shared.models.pi0  # noqa: F401
    import shared.models.smolvla  # noqa: F401
    import shared.models.toy  # noqa: F401
    import shared.models.xr0  # noqa: F401

    # A user's own architectures, for tools run without a config (`robion models`): the modules named in
    # ROBION_IMPORTS (comma-separated). A config lists them under `imports` (shared/config.py).
    for name in filter(None, (n.strip() for n in os.environ.get("ROBION_IMPORTS", "").split(","))):
        try:
            importlib.import_module(name)
        except Exception as exc:
            raise ImportError(f"ROBION_IMPORTS: cannot import {name!r} ({type(exc).__name__}: {exc})") from exc
