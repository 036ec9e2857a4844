"""Registry of two-stage VLA architectures, so users can serve their own."""

from __future__ import annotations

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
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = cls(configs[size])
    model.eval().requires_grad_(False)
    if dtype is None:
        dtype = torch.bfloat16 if torch.device(device).type == "cuda" else torch.float32
    return model.to(device=device, dtype=dtype)


def _load_builtin() -> None:
    # Importing the architecture modules runs their @register decorators.
    import shared.models.toy  # noqa: F401
