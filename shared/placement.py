"""Does a placement fit? Device memory each executor's models need, estimated before loading.

Per model: weights (bf16 on a GPU) + the copies of the action stage's QKV and gate/up weights
with the norm weights folded in (``layers.folded_weight``) + the engine's static buffers (inputs, handoff twice: the
VLM output and the action input, outputs) for every batch size up to max_batch + a working
margin for the graphs' activation pools (a share of the weights plus a per-batch amount,
chosen to cover the zoo's measured peaks on the H100, where SmolVLA's 512x512 vision tower
makes activations large next to its weights). Per executor: a fixed overhead for the CUDA context,
cuBLAS workspaces and green contexts.
"""

from __future__ import annotations

from functools import lru_cache

from shared.config import ClusterConfig, ConfigError

GIB = 1024**3
CONTEXT_OVERHEAD = int(1.0 * GIB)
ACTIVATION_SHARE = 0.15  # of the weights
ACTIVATION_PER_BATCH = int(0.25 * GIB)  # per unit of max_batch


@lru_cache(maxsize=64)
def model_bytes(arch: str, size: str, max_batch: int, dtype_bytes: int = 2) -> int:
    from shared.models.registry import build_meta, build_model

    try:
        return _estimate(build_meta(arch, size), max_batch, dtype_bytes)
    except Exception:
        # A user's class whose constructor (or handoff_spec) reads a tensor's value cannot run on the meta device
        # (docs/models.md); its executor builds it for real, so the estimate does too, once, on the CPU.
        pass
    try:
        return _estimate(build_model(arch, size, device="cpu"), max_batch, dtype_bytes)
    except Exception as exc:
        raise ConfigError(f"cannot estimate the memory of {arch} ({size}): {type(exc).__name__}: {exc}") from exc


def _estimate(model, max_batch: int, dtype_bytes: int) -> int:
    import torch

    weights = (sum(p.numel() for p in model.parameters()) + _folded_params(model)) * dtype_bytes
    buffers = 0
    b = 1
    while b <= max_batch:
        spec = model.handoff_spec(b)
        handoff = sum(torch.Size(shape).numel() * torch.empty((), dtype=dt).element_size() for shape, dt in spec.values())
        io = model.io
        inputs = b * (len(io.cameras) * io.image_shape[0] * io.image_shape[1] * 3 + 4 * io.state_dim + 8 * io.prompt_len)
        outputs = b * io.horizon * io.action_dim * 4 * 3  # noise, device output, pinned copies
        buffers += 2 * handoff + 2 * inputs + outputs
        b *= 2
    return int(weights * (1 + ACTIVATION_SHARE) + ACTIVATION_PER_BATCH * max_batch + buffers)


def _folded_params(model) -> int:
    """Parameters of the norm-folded weight copies that the fused action stages make: the QKV (or
    query) and gate/up weights of every action layer with an RMSNorm before its MLP (a slight
    over-count: the first layer's QKV input never has row statistics)."""
    from shared.models.layers import RMSNorm

    n = 0
    for name in getattr(model, "ACTION_MODULES", ()):
        for mod in getattr(model, name).modules():
            if not isinstance(getattr(mod, "mlp_norm", None), RMSNorm) or not hasattr(mod.mlp, "gate_up"):
                continue
            n += mod.mlp.gate_up.weight.numel()
            lin = getattr(getattr(mod, "attn", None), "qkv", None) or getattr(mod, "q", None)
            n += lin.weight.numel() if lin is not None else 0
    return n


def memory_shortfall(cfg: ClusterConfig, executor: str, models: list[str], have: int) -> str | None:
    """Why ``models`` do not fit in ``have`` bytes on ``executor`` (CUDA context included); None when they fit."""
    # Fine-tuned variants of one architecture still hold their own weights.
    each = {m: model_bytes(cfg.model(m).arch, cfg.model(m).size, cfg.engine.max_batch) for m in models}
    need = CONTEXT_OVERHEAD + sum(each.values())
    if need <= have:
        return None
    per = ", ".join(f"{m} {b / GIB:.1f}" for m, b in each.items())
    return (f"the models placed on {executor} need about {need / GIB:.1f} GiB ({per} GiB, plus "
            f"{CONTEXT_OVERHEAD / GIB:.0f} GiB for the CUDA context) but it has {have / GIB:.1f} GiB: place fewer "
            "models there, or add a GPU")


def check_fit(cfg: ClusterConfig, free_bytes: dict[str, int] | None = None) -> None:
    """Raise ConfigError naming the first executor whose models do not fit its memory.

    Memory comes from ``free_bytes`` (measured on the device) or the config's ``memory_gb``;
    executors with neither are not checked.
    """
    for j, ex in enumerate(cfg.executors):
        have = (free_bytes or {}).get(ex.name)
        if have is None and ex.memory_gb is not None:
            have = int(ex.memory_gb * GIB)
        if have is None:
            continue
        short = memory_shortfall(cfg, ex.name, ex.models, have)
        if short is not None:
            raise ConfigError(f"executors[{j}].models: {short}")
