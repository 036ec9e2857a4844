"""The executor's engine: takes validated requests, runs the two stages, reports results.

The I/O layer only calls ``submit`` and receives results through ``on_results``; which
engine runs behind it (the monolithic pipeline here, the two-stream lockstep engine, the
comparison engines) is a configuration choice.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Callable

import torch

from services.executor.scheduler import ModelQueues, Request, Result
from services.executor.stages import EagerStages
from shared.config import EngineConfig
from shared.models.base import VLAModel
from shared.protocol import ErrorCode

log = logging.getLogger(__name__)

ResultSink = Callable[[list[Result]], None]


@dataclass
class ServedModel:
    name: str
    model: VLAModel
    slo_s: float


class Engine:
    """Queues plus a loop; subclasses define one scheduling step."""

    def __init__(self, models: dict[str, ServedModel], cfg: EngineConfig, device: torch.device, on_results: ResultSink):
        self.models = models
        self.cfg = cfg
        self.device = device
        self.on_results = on_results
        self.queues = ModelQueues(list(models), cfg.max_queue, cfg.policy, cfg.shed_expired)

    def submit(self, req: Request) -> None:
        """Thread-safe; raises ProtocolError (OVERLOADED, UNKNOWN_MODEL) when it cannot queue."""
        self.queues.put(req)

    def prepare(self) -> None:
        """One-time start-up work (warm-up, graph capture) before serving."""

    def step(self) -> bool:
        """Run one scheduling step; False when there was nothing to do."""
        raise NotImplementedError

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                if not self.step():
                    self.queues.wait(0.005)
            except Exception:  # a fault in one batch must not stop the executor
                log.exception("engine step failed")
        self.finish()

    def finish(self) -> None:
        """Answer everything still queued at shutdown."""
        pending = self.queues.drain()
        if pending:
            self.on_results([Result(r, error=(ErrorCode.UNAVAILABLE, "executor is shutting down")) for r in pending])

    def _report_expired(self, expired: list[Request]) -> None:
        if expired:
            self.on_results([Result(r, error=(ErrorCode.DEADLINE_EXCEEDED, "deadline passed while queued"))
                             for r in expired])


class MonolithicEngine(Engine):
    """VLM then action stage as one pipeline on one stream, one batch at a time."""

    def __init__(self, models, cfg, device, on_results):
        super().__init__(models, cfg, device, on_results)
        self.stages = {name: EagerStages(m.model, device, seed=cfg.seed) for name, m in models.items()}

    def prepare(self) -> None:
        # One pass per batch size so allocator and kernel caches are warm before the first robot.
        b = 1
        while b <= self.cfg.max_batch:
            for st in self.stages.values():
                images, state, tokens = st.model.example_inputs(b, self.device)
                st.action(st.vlm(images, state, tokens), st.model.noise(b, self.device))
            b *= 2

    def step(self) -> bool:
        model, batch, expired = self.queues.take(self.cfg.max_batch)
        self._report_expired(expired)
        if not batch:
            return bool(expired)
        st = self.stages[model]
        admitted = time.monotonic()
        try:
            images, state, tokens, noise = st.inputs(batch)
            handoff = st.vlm(images, state, tokens)
            _sync(self.device)
            t_vlm = time.monotonic()
            actions = st.action(handoff, noise).float().cpu().numpy()
            t_act = time.monotonic()
        except Exception as exc:
            log.exception("batch of %d for %s failed", len(batch), model)
            self.on_results([Result(r, error=(ErrorCode.INTERNAL, f"inference failed: {type(exc).__name__}"))
                             for r in batch])
            return True
        self.on_results([Result(r, actions=actions[i], admitted=admitted, vlm_s=t_vlm - admitted,
                                action_s=t_act - t_vlm, done=t_act) for i, r in enumerate(batch)])
        return True


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


ENGINES: dict[str, type[Engine]] = {"monolithic": MonolithicEngine}


def make_engine(models: dict[str, ServedModel], cfg: EngineConfig, device: torch.device, on_results: ResultSink) -> Engine:
    import services.executor.lockstep  # noqa: F401  (registers "robion"; imported late: it builds on this module)

    if cfg.kind not in ENGINES:
        raise ValueError(f"engine {cfg.kind!r} is not available; available: {', '.join(ENGINES)}")
    return ENGINES[cfg.kind](models, cfg, device, on_results)
