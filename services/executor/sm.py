"""SM restriction of the VLM stage: green contexts, SM levels and the policies that pick one.

A *level* is the number of SMs the VLM stage may occupy during one lockstep; ``None`` means
unrestricted. The guarded design keeps one green context per level, all starting from the
same low SMs (each ``GreenContext.create`` splits the device on its own), while the action
stage runs on a plain stream and may use every SM (unless the SM table confined its action
graph to a level's ``complement``). CUDA graphs keep the SM limit of the
stream they were captured on, so the green streams are needed for capture (and for eager
VLM launches); replaying a restricted graph works from any stream.

Nothing here touches CUDA at import time: the CPU engine imports this module too.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Protocol

import torch

log = logging.getLogger(__name__)

Level = int | None  # SMs the VLM stream may use; None: unrestricted
SM_GRANULARITY = 8  # Hopper's minimum and step for cuDevSmResourceSplitByCount


def sm_count(device: torch.device) -> int:
    return torch.cuda.get_device_properties(device).multi_processor_count


def sm_levels(total_sms: int, step: int = SM_GRANULARITY) -> list[Level]:
    """Every restriction the device supports (multiples of ``step`` below the SM count) plus unrestricted."""
    return [n for n in range(step, total_sms, step)] + [None]


def level_name(level: Level) -> str:
    return "none" if level is None else str(level)


def parse_level(text: str) -> Level:
    return None if text == "none" else int(text)


def green_contexts_available() -> bool:
    if not torch.cuda.is_available():
        return False
    try:
        from torch.cuda import green_contexts
    except ImportError:
        return False
    return bool(getattr(green_contexts, "SUPPORTED", hasattr(green_contexts, "GreenContext")))


class GreenStreams:
    """One green context and stream per SM level, created once at start-up.

    The context objects are kept here for the life of the engine: a stream or a captured
    graph whose green context was destroyed is undefined behaviour, not an error.
    """

    def __init__(self, device: torch.device, levels: list[Level]):
        from torch.cuda.green_contexts import GreenContext

        self.device = device
        self.total_sms = sm_count(device)
        self._contexts: dict[int, Any] = {}
        self._streams: dict[int, torch.cuda.Stream] = {}
        self._complements: dict[int, "DisjointPartition"] = {}
        for level in sorted({lv for lv in levels if lv is not None}):
            self._check(level)
            ctx = GreenContext.create(num_sms=level, device_id=device.index or 0)
            self._contexts[level] = ctx
            self._streams[level] = ctx.Stream()
        log.info("green contexts for SM levels %s of %d", sorted(self._streams), self.total_sms)

    def _check(self, level: int) -> None:
        if level % SM_GRANULARITY or not 0 < level < self.total_sms:
            raise ValueError(f"SM level {level} is not a multiple of {SM_GRANULARITY} below {self.total_sms}")

    @property
    def levels(self) -> list[int]:
        return sorted(self._streams)

    def stream(self, level: int) -> torch.cuda.Stream:
        return self._streams[level]

    def complement(self, level: int) -> tuple[torch.cuda.Stream, int]:
        """A stream on the SMs a VLM at ``level`` leaves free, and their count (created on first
        use, kept for the engine's life). It comes from the same split by count as the level's
        own context, which takes the low SMs, so work confined here never shares an SM with
        a VLM graph of that level (or lower)."""
        if level not in self._complements:
            self._check(level)
            self._complements[level] = split_disjoint(self.device, level)
        part = self._complements[level]
        return part.action_stream, part.action_sms


@dataclass
class DisjointPartition:
    """Two green contexts over disjoint SM groups (the disjoint-partition ablation)."""

    vlm_sms: int
    action_sms: int
    vlm_stream: torch.cuda.Stream
    action_stream: torch.cuda.Stream
    keepalive: list[Any] = field(default_factory=list)  # driver green contexts and resources


def split_disjoint(device: torch.device, vlm_sms: int) -> DisjointPartition:
    """Split the device once into ``vlm_sms`` SMs and the remainder, one green stream each.

    Separate ``GreenContext.create`` calls overlap (all start from SM 0), so a true
    partition goes through the driver: ``cuDevSmResourceSplitByCount`` returns the group
    and the remaining SMs, and each becomes its own green context.
    """
    from cuda.bindings import driver

    def check(result: tuple) -> Any:
        err, *rest = result
        if err != driver.CUresult.CUDA_SUCCESS:
            raise RuntimeError(f"CUDA driver call failed: {err!r}")
        return rest[0] if len(rest) == 1 else rest

    torch.cuda.init()
    dev = check(driver.cuDeviceGet(device.index or 0))
    whole = check(driver.cuDeviceGetDevResource(dev, driver.CUdevResourceType.CU_DEV_RESOURCE_TYPE_SM))
    groups, _n, remainder = check(driver.cuDevSmResourceSplitByCount(1, whole, 0, vlm_sms))
    streams, keep = [], [whole, groups, remainder]
    for res in (groups[0], remainder):
        desc = check(driver.cuDevResourceGenerateDesc([res], 1))
        gctx = check(driver.cuGreenCtxCreate(desc, dev, driver.CUgreenCtxCreate_flags.CU_GREEN_CTX_DEFAULT_STREAM))
        raw = check(driver.cuGreenCtxStreamCreate(gctx, driver.CUstream_flags.CU_STREAM_NON_BLOCKING, 0))
        keep += [desc, gctx, raw]
        streams.append(torch.cuda.ExternalStream(int(raw), device=device))
    return DisjointPartition(groups[0].sm.smCount, remainder.sm.smCount, streams[0], streams[1], keep)


# ----------------------------------------------------------------------------- policies

class SMPolicy(Protocol):
    """Chooses the VLM stream's SM level at each lockstep start."""

    name: str

    def level(self, vlm_arch: str, vlm_batch: int, action_arch: str | None, action_batch: int) -> Level: ...

    def levels_for(self, vlm_arch: str, vlm_batch: int) -> set[Level]:
        """Levels a VLM graph of this (architecture, batch) may be replayed at: capture these."""
        ...


class Unrestricted:
    """Stage disaggregation without SM restriction (an ablation, and the CPU engine)."""

    name = "none"

    def level(self, vlm_arch: str, vlm_batch: int, action_arch: str | None, action_batch: int) -> Level:
        return None

    def levels_for(self, vlm_arch: str, vlm_batch: int) -> set[Level]:
        return {None}


@dataclass
class StaticLevel:
    """The VLM stream always restricted to the same SM count (static-restriction ablation)."""

    sms: int
    name: str = "static"

    def level(self, vlm_arch: str, vlm_batch: int, action_arch: str | None, action_batch: int) -> Level:
        return self.sms

    def levels_for(self, vlm_arch: str, vlm_batch: int) -> set[Level]:
        return {self.sms}


@dataclass
class TableLevel:
    """Robion's guarded dynamic restriction: the profiled best level per co-running pair.

    ``best`` maps (vlm arch, vlm batch, action arch, action batch) to a level. A VLM stage
    running alone is never restricted: nothing would use the SMs it gives up.
    """

    best: dict[tuple[str, int, str, int], Level]
    name: str = "table"

    def level(self, vlm_arch: str, vlm_batch: int, action_arch: str | None, action_batch: int) -> Level:
        if action_arch is None:
            return None
        return self.best.get((vlm_arch, vlm_batch, action_arch, action_batch))

    def levels_for(self, vlm_arch: str, vlm_batch: int) -> set[Level]:
        return {None} | {lv for (va, vb, _, _), lv in self.best.items() if va == vlm_arch and vb == vlm_batch}
