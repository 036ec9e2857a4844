"""Save and load a zoo model's own state dict as safetensors, with strict checks.

A fine-tuned variant of an architecture is the same class with other weights: another
seed (``build_model(arch, seed=7)``) or another file (``load_model(arch, path=...)``).
Key names are the zoo's own (``model.state_dict()``); real checkpoints must be
converted to them (see docs/models.md for the layout conventions).
"""

from __future__ import annotations

import os

import torch

from shared.models.base import VLAModel
from shared.models.registry import build_model


class WeightsError(ValueError):
    """A checkpoint does not match the model: missing or unexpected keys, wrong shapes or dtypes, values that
    are not finite."""


# safetensors dtype names of floating-point tensors (the file's header, as get_slice().get_dtype() gives it).
FLOAT_DTYPES = {"F64", "F32", "F16", "BF16", "F8_E4M3", "F8_E5M2"}
INT_DTYPES = {"I64", "I32", "I16", "I8", "U64", "U32", "U16", "U8"}


def _names(names: list[str], limit: int = 8) -> str:
    shown = ", ".join(sorted(names)[:limit])
    return shown + (f", ... ({len(names) - limit} more)" if len(names) > limit else "")


def save_weights(model: VLAModel, path: str) -> None:
    """Write the model's state dict (in its current dtype) to a safetensors file."""
    from safetensors.torch import save_file

    # safetensors refuses tensors that share memory (tied parameters: one tensor under two keys). Each key gets
    # its own copy of a shared one, so the file has every key load_weights expects; loading assigns the same
    # values to both, which keeps them tied.
    tensors, seen = {}, set()
    for k, v in model.state_dict().items():
        v = v.detach()
        ptr = (v.untyped_storage().data_ptr(), v.device) if v.numel() else None
        tensors[k] = v.clone() if ptr in seen else v.contiguous()
        if ptr is not None:
            seen.add(ptr)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    save_file(tensors, path, metadata={"arch": model.arch, "format": "robion-zoo-1"})


def load_weights(model: VLAModel, path: str) -> VLAModel:
    """Load a safetensors file into ``model`` in place; keys and shapes must match exactly.

    Tensors are cast to each parameter's dtype and device. Raises FileNotFoundError or
    WeightsError (naming the offending keys, shapes or dtypes, a tensor whose values are not finite
    in the parameter's dtype, or saying the file is no safetensors file) and leaves the model
    untouched on error.
    """
    from safetensors import SafetensorError, safe_open

    if os.path.isdir(path):
        raise IsADirectoryError(f"weights file {path} is a directory")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"weights file not found: {path}")
    if not os.access(path, os.R_OK):  # the library says "No such file or directory" for a file it may not read
        raise PermissionError(f"weights file {path} cannot be read (permission denied)")
    expected = model.state_dict()
    try:
        opened = safe_open(path, framework="pt", device="cpu")
    except SafetensorError as exc:
        # e.g. a torch.save checkpoint: the library's own message ("header too large") does not say
        # that, and its exception is no ValueError, so a service loading the file would crash.
        raise WeightsError(f"{path} is not a safetensors file ({exc})") from None
    with opened as f:
        meta = f.metadata() or {}
        keys = set(f.keys())
        problems = []
        missing = sorted(set(expected) - keys)
        unexpected = sorted(keys - set(expected))
        if missing:
            problems.append(f"{len(missing)} missing key(s): {_names(missing)}")
        if unexpected:
            problems.append(f"{len(unexpected)} unexpected key(s): {_names(unexpected)}")
        bad, kinds = [], []
        for k in sorted(keys & set(expected)):
            part = f.get_slice(k)
            shape = tuple(part.get_shape())
            if shape != tuple(expected[k].shape):
                bad.append(f"{k}: file {list(shape)} vs model {list(expected[k].shape)}")
            # A cast cannot turn integers, booleans or scale-only formats into trained floating-point weights:
            # such a tensor is another file's, or a corrupted one.
            want = expected[k].dtype
            if want.is_floating_point:
                fits = part.get_dtype() in FLOAT_DTYPES
            else:
                # An index or a mask: a float file would be truncated to other integers (NaN to -2**63) or read
                # as True/False, silently. Integers load into integers, booleans into booleans.
                fits = part.get_dtype() == "BOOL" if want == torch.bool else part.get_dtype() in INT_DTYPES
            if not fits:
                kinds.append(f"{k}: file {part.get_dtype()} vs model {str(want).removeprefix('torch.')}")
        if bad:
            problems.append(f"{len(bad)} shape mismatch(es): " + "; ".join(bad[:8]) +
                            (f"; ... ({len(bad) - 8} more)" if len(bad) > 8 else ""))
        if kinds:
            problems.append(f"{len(kinds)} tensor(s) of a dtype that cannot hold the model's values: " + "; ".join(kinds[:8]) +
                            (f"; ... ({len(kinds) - 8} more)" if len(kinds) > 8 else ""))
        if problems:
            arch = meta.get("arch")
            hint = f" (file was saved from {arch!r}, model is {model.arch!r})" if arch and arch != model.arch else ""
            raise WeightsError(f"{path} does not fit {model.arch or type(model).__name__}{hint}: " + " | ".join(problems))
        # Checked before any parameter changes, so a bad file leaves the model as it was: a NaN in the file, or a
        # value beyond the range of the parameter's dtype (a float64 1e39 is inf as float32 or bf16), would make
        # every reply NaN actions. Two passes, one tensor at a time, rather than a staged copy of the whole model.
        for k, dst in expected.items():
            if dst.is_floating_point() and not bool(torch.isfinite(f.get_tensor(k).to(dst.device, dst.dtype)).all()):
                raise WeightsError(f"{path}: {k} holds NaN or infinite values as {str(dst.dtype).removeprefix('torch.')}")
        with torch.no_grad():
            for k, dst in expected.items():
                dst.copy_(f.get_tensor(k).to(dtype=dst.dtype))
    return model


def load_model(arch: str, size: str = "full", path: str | None = None, seed: int = 0,
               device: str | torch.device = "cpu", dtype: torch.dtype | None = None) -> VLAModel:
    """Build an architecture and, when ``path`` is given, load its weights from that file."""
    model = build_model(arch, size, seed=seed, device=device, dtype=dtype)
    return load_weights(model, path) if path is not None else model
