"""The models an executor hosts and the engine serving them, replaceable at run time.

A placement change reloads the executor: the control plane first takes it out of routing,
the executor waits until every request it holds is answered, then builds the new model set
(weights already loaded are kept) and a fresh engine (graphs, SM table from the cache), and
registers again. Other executors keep serving meanwhile.
"""

from __future__ import annotations

import gc
import logging
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from services.executor.engine import Engine, ServedModel, make_engine
from services.executor.scheduler import Request, Result
from services.executor.tokens import tokenizer_for
from shared.config import EngineConfig, ModelConfig
from shared.models import build_model
from shared.models.base import ModelIO, VLAModel, check_interface
from shared.protocol import ErrorCode, ModelInfo, ProtocolError

log = logging.getLogger("robion.executor")


@dataclass
class ServedInput:
    """What the I/O thread needs to validate and prepare a model's requests."""

    io: ModelIO
    slo_s: float
    tokenize: Callable[[str], np.ndarray]
    info: ModelInfo
    config: ModelConfig


@dataclass
class Hosted:
    models: dict[str, ServedModel]
    inputs: dict[str, ServedInput]


def free_memory() -> None:
    """Collect what nothing references any more (cycles included) and return CUDA's cached blocks, so a build that
    follows finds the memory free (best effort; a no-op for CUDA where this process never used it)."""
    gc.collect()
    try:
        if torch.cuda.is_available():
            torch.cuda.empty_cache()
    except Exception:
        log.debug("could not empty the CUDA cache", exc_info=True)


def _weights_key(mc: ModelConfig) -> tuple:
    return (mc.arch, mc.size, mc.seed, mc.weights)


class ModelStore:
    """Builds models from their configs; weights already on the device are reused by identity."""

    def __init__(self, device: torch.device, max_batch: int = 2):
        self.device = device
        self.max_batch = max_batch
        self._loaded: dict[tuple, VLAModel] = {}

    def load(self, configs: list[ModelConfig]) -> Hosted:
        wanted = {_weights_key(mc) for mc in configs}
        for key in [k for k in self._loaded if k not in wanted]:
            del self._loaded[key]  # unloaded: its memory goes back once no engine holds it
        models, inputs = {}, {}
        for mc in configs:
            key = _weights_key(mc)
            if key not in self._loaded:
                model = build_model(mc.arch, mc.size, seed=mc.seed, device=self.device)
                if mc.weights is not None:
                    from shared.models.weights import load_weights

                    load_weights(model, mc.weights)
                # Before an engine copies its outputs into buffers they may not fit; at batch 2 only where batches of
                # 2 will be formed (a model served at max_batch 1 may take one robot at a time).
                check_interface(model, batches=(1, 2) if self.max_batch >= 2 else (1,))
                self._loaded[key] = model
                log.info("loaded %s (%s/%s, seed %d) on %s", mc.name, mc.arch, mc.size, mc.seed, self.device)
            model = self._loaded[key]
            io = model.io
            models[mc.name] = ServedModel(mc.name, model, mc.slo_ms / 1e3)
            info = ModelInfo(cameras=list(io.cameras), image_shape=list(io.image_shape), state_dim=io.state_dim,
                             horizon=io.horizon, action_dim=io.action_dim, deadline_ms=mc.slo_ms, arch=mc.arch)
            inputs[mc.name] = ServedInput(io=io, slo_s=mc.slo_ms / 1e3, tokenize=tokenizer_for(model, mc.tokenizer),
                                          info=info, config=mc)
        return Hosted(models, inputs)


class EngineSlot:
    """The engine serving now and its thread; requests arriving while it is replaced are refused."""

    def __init__(self, cfg: EngineConfig, device: torch.device, on_results: Callable[[list[Result]], None]):
        self.cfg = cfg
        self.device = device
        self.on_results = on_results
        self.engine: Engine | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()

    def start(self, hosted: Hosted) -> float:
        """Build, prepare (graphs, profiling) and start an engine; returns the seconds it took."""
        t0 = time.monotonic()
        engine = make_engine(hosted.models, self.cfg, self.device, self.on_results)
        engine.prepare()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=engine.run, args=(self._stop,), name="engine", daemon=True)
        self._thread.start()
        with self._lock:
            self.engine = engine
        return time.monotonic() - t0

    def start_while(self, hosted: Hosted, meanwhile: Callable[[threading.Event], None]) -> float:
        """``start`` on a thread of its own while ``meanwhile(started)`` runs on this one (it returns once
        ``started`` is set, or earlier); returns the seconds ``start`` took, or raises what it raised."""
        started = threading.Event()
        outcome: dict = {}

        def start() -> None:
            try:
                outcome["took"] = self.start(hosted)
            except BaseException as exc:  # raised again on the caller's thread
                outcome["error"] = exc
            finally:
                started.set()

        threading.Thread(target=start, name="engine-start", daemon=True).start()
        meanwhile(started)
        started.wait()
        if "error" in outcome:
            raise outcome["error"]
        return outcome["took"]

    def stop(self, timeout_s: float = 30.0) -> None:
        """Stop the engine; whatever it still holds is answered by its ``finish``."""
        with self._lock:
            engine, self.engine = self.engine, None
        if engine is None:
            return
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.error("engine thread did not stop within %.0f s", timeout_s)
        close = getattr(engine, "close", None)
        if close is not None:  # engines with worker processes (procdisagg) stop them here
            close()

    def failed(self) -> bool:
        """The engine's loop ended without a stop (a fault it could not go on from, e.g. a stage process of
        procdisagg that died): every request would be refused from now on."""
        with self._lock:
            engine = self.engine
        return engine is not None and self._thread is not None and not self._thread.is_alive() and \
            not self._stop.is_set()

    def submit(self, req: Request) -> None:
        with self._lock:
            engine = self.engine
        if engine is None:
            raise ProtocolError(ErrorCode.UNAVAILABLE, "executor is starting or changing its models; retry")
        engine.submit(req)

    def depths(self) -> dict[str, int]:
        with self._lock:
            engine = self.engine
        return engine.queues.depths() if engine is not None else {}
