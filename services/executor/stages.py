"""Running a model's two stages on a batch of requests.

The CPU path runs the stages eagerly. The GPU path (CUDA graphs per stage and batch size,
static handoff buffers, SM levels) plugs in behind the same methods, so engines never
care which one they drive.
"""

from __future__ import annotations

import numpy as np
import torch

from services.executor.scheduler import Request
from shared.models.base import Handoff, VLAModel


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
