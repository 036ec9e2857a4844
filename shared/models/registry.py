"""Registry of two-stage VLA architectures, so users can serve their own."""

from __future__ import annotations

import importlib
import os
import sys

import torch

from shared.models.base import VLAModel

_ARCHS: dict[str, type[VLAModel]] = {}
BUILTIN_MODULES = ("shared.models.groot_n15", "shared.models.pi0", "shared.models.smolvla", "shared.models.toy",
                   "shared.models.xr0")


def register(name: str):
    """Class decorator: ``@register("my_vla")`` makes an architecture servable by name.

    The class needs a ``CONFIGS`` dict mapping size names ("full", "tiny", ...) to its
    config dataclass (a "full" size is what ``robion models`` lists) and a constructor
    taking that config. A name already taken, the built-ins' included, is refused here,
    in the module that registers it.
    """

    if not isinstance(name, str) or not name:
        # `@register` without a name passed the class as the name and returned `wrap` in its place: the class
        # became a function, and the failure surfaced later as "unknown architecture".
        raise TypeError(f"register takes the architecture's name: use @register(\"my_vla\"), "
                        f"got {type(name).__name__}")

    def wrap(cls: type[VLAModel]) -> type[VLAModel]:
        if not (isinstance(cls, type) and issubclass(cls, VLAModel)):
            raise TypeError(f"@register({name!r}) needs a VLAModel subclass, got {cls!r}")
        configs = getattr(cls, "CONFIGS", None)
        if not isinstance(configs, dict) or not all(isinstance(k, str) for k in configs):
            # Read as a mapping by the config's checks and `robion models`: anything else failed there as a TypeError.
            raise TypeError(f"@register({name!r}): {cls.__name__}.CONFIGS must be a dict of size name -> config, "
                            f"got {type(configs).__name__}")
        if cls.__module__ not in BUILTIN_MODULES:
            # The built-ins first: a user's module imported before them could otherwise take "pi0", and the
            # clash would surface later as an error inside shared/models/pi0.py, blaming the wrong module.
            _load_builtin_archs()
        if name in _ARCHS and _ARCHS[name] is not cls:
            raise ValueError(f"architecture {name!r} is already registered (by {_ARCHS[name].__module__})")
        if cls.__dict__.get("arch") and cls.__dict__["arch"] != name:
            # One class under two names would rename the first: its models would report, and save into their
            # weight files, the second name.
            raise ValueError(f"{cls.__name__} is already registered as {cls.__dict__['arch']!r}; "
                             f"subclass it to register it as {name!r} too")
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
    generator = torch.Generator(device).manual_seed(seed)
    try:
        with torch.device("meta"):
            model = cls(configs[size])
    except Exception:  # a constructor that needs real values (e.g. `.item()` of a drop-path schedule)
        model = None
    if (model is not None and type(model).init_weights is not VLAModel.init_weights
            and next(model.buffers(), None) is None and not _shares_parameters(model)):
        # Its own init sets every parameter: build on the meta device and materialise straight in the target
        # dtype on the target device, so a 4.7 B-parameter model never exists as fp32 on the host.
        model = model.to(dtype=dtype).to_empty(device=device)
    else:
        # Memory from to_empty is uninitialised, and only a constructor knows how to fill what the default
        # init (reset_parameters) does not reach: buffers, bare nn.Parameters, layers such as
        # nn.MultiheadAttention that initialise in _reset_parameters. Such a model is constructed for real,
        # on its device under the seed (same seed, same weights), then cast. So is one whose constructor cannot
        # run on the meta device, and one with tied parameters (to_empty gives each name a tensor of its own).
        devices = [device.index] if device.type == "cuda" else []
        with torch.random.fork_rng(devices=devices), torch.device(device):
            torch.manual_seed(seed)
            model = cls(configs[size])
        model = model.to(dtype=dtype)
    model.init_weights(generator)
    return model.eval().requires_grad_(False)


def _shares_parameters(model: torch.nn.Module) -> bool:
    """Whether one parameter is reachable under two names (tied weights)."""
    params = [p for _, p in model.named_parameters(remove_duplicate=False)]
    return len({id(p) for p in params}) < len(params)


def build_meta(arch: str, size: str = "full") -> VLAModel:
    """The architecture on the meta device: shapes and parameter counts, no memory."""
    cls = get_architecture(arch)
    with torch.device("meta"):
        return cls(cls.CONFIGS[size])


def _load_builtin_archs() -> None:
    # Importing the architecture modules runs their @register decorators.
    for module in BUILTIN_MODULES:
        importlib.import_module(module)


def _load_builtin() -> None:
    _load_builtin_archs()
    # A user's own architectures, for tools run without a config (`robion models`): the modules named in
    # ROBION_IMPORTS (comma-separated). A config lists them under `imports` (shared/config.py). The working
    # directory is searched after sys.path: the `robion` script, unlike `python -m`, does not put it there.
    names = [n for n in (n.strip() for n in os.environ.get("ROBION_IMPORTS", "").split(",")) if n]
    if names and os.getcwd() not in sys.path and "" not in sys.path:
        sys.path.append(os.getcwd())
    for name in names:
        try:
            importlib.import_module(name)
        except Exception as exc:
            raise ImportError(f"ROBION_IMPORTS: cannot import {name!r} ({type(exc).__name__}: {exc})") from exc
