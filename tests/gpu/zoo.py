"""What the GPU tests share: seeded requests for a zoo model, the eager reference and the
error of served replies against it, and matmul timing on SM-partition streams."""

from __future__ import annotations

import time
from typing import Mapping

import numpy as np
import torch

from services.executor.scheduler import Request, Result

DEV = torch.device("cuda:0")


def requests(model, name: str, n: int, seed: int) -> list[Request]:
    """``n`` requests for ``model`` served as ``name``: random uint8 images, state, prompt and noise."""
    rng = np.random.default_rng(seed)
    io = model.io
    now = time.monotonic()
    return [Request(id=f"{name}-{i}", robot=f"r{i}", model=name,
                    images=rng.integers(0, 256, (len(io.cameras), *io.image_shape), dtype=np.uint8),
                    state=rng.standard_normal(io.state_dim).astype(np.float32),
                    tokens=rng.integers(1, 200, io.prompt_len).astype(np.int64), arrival=now, deadline=now + 600,
                    noise=rng.standard_normal((io.horizon, io.action_dim)).astype(np.float32)) for i in range(n)]


def eager(model, r: Request) -> np.ndarray:
    """The request's actions from the model run eagerly at batch 1 (no engine, no graphs)."""
    with torch.inference_mode():
        h = model.vlm_stage(torch.from_numpy(r.images)[None].to(DEV), torch.from_numpy(r.state)[None].to(DEV),
                            torch.from_numpy(r.tokens)[None].to(DEV))
        return model.action_stage(h, torch.from_numpy(r.noise)[None].to(DEV))[0].float().cpu().numpy()


def worst_error_vs_eager(models: Mapping[str, object], results: list[Result], n: int) -> float:
    """Checks that ``n`` distinct requests were answered without error; returns the largest
    relative error of a reply against ``eager`` of its model."""
    assert len(results) == n and len({r.request.id for r in results}) == n
    worst = 0.0
    for res in results:
        assert res.error is None, res.error
        ref = eager(models[res.request.model], res.request)
        worst = max(worst, float(np.linalg.norm(res.actions - ref) / np.linalg.norm(ref)))
    return worst


def matmul_ms(streams: Mapping[str, torch.cuda.Stream]) -> dict[str, float]:
    """Milliseconds of one 8192^3 bf16 matmul on each stream (after a warm-up one): how many
    SMs a partition's stream really gets."""
    a = torch.randn(8192, 8192, device=DEV, dtype=torch.bfloat16)
    times = {}
    for name, stream in streams.items():
        stream.wait_stream(torch.cuda.current_stream())
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        with torch.cuda.stream(stream):
            a @ a
            start.record(stream)
            for _ in range(5):
                a @ a
            end.record(stream)
        end.synchronize()
        times[name] = start.elapsed_time(end) / 5
    return times


def blas_settings() -> tuple:
    """torch's process-wide GEMM settings that ``graphs.gemm_sm_target`` changes during a capture."""
    return torch.backends.cuda.preferred_blas_library(), torch._C._get_sm_carveout_experimental()
