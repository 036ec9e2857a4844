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
from shared.protocol import ErrorCode, ProtocolError

log = logging.getLogger(__name__)

ResultSink = Callable[[list[Result]], None]


@dataclass
class ServedModel:
    name: str
    model: VLAModel
    slo_s: float


def timed_sink(queues: ModelQueues, sink: ResultSink) -> ResultSink:
    """``sink`` that also tells ``queues`` each answered request's service time (``shed_late``).

    It holds the queues, not the engine: an engine holding a closure over itself is a reference cycle, and
    a stopped engine (its models, on a GPU their weights and graphs) then lived on until a full garbage
    collection, through the reload that needed the memory."""
    def deliver(results: list[Result]) -> None:
        for r in results:
            if r.actions is not None and r.admitted > 0:
                queues.note_service(r.request.model, r.done - r.admitted)
        sink(results)
    return deliver


class Engine:
    """Queues plus a loop; subclasses define one scheduling step."""

    def __init__(self, models: dict[str, ServedModel], cfg: EngineConfig, device: torch.device, on_results: ResultSink):
        self.models = models
        self.cfg = cfg
        self.device = device
        self.queues = ModelQueues(list(models), cfg.max_queue, cfg.policy, cfg.shed_expired, cfg.shed_late)
        self.on_results = timed_sink(self.queues, on_results) if cfg.shed_late else on_results
        # Noise is drawn when a request arrives (seeded per model, in arrival order), off the
        # path between batches; a request may bring its own.
        self._noise_gens = {name: torch.Generator().manual_seed(cfg.seed) for name in models}
        self._noise_lock = threading.Lock()

    def submit(self, req: Request) -> None:
        """Thread-safe; raises ProtocolError (OVERLOADED, UNKNOWN_MODEL) when it cannot queue."""
        gen = self._noise_gens.get(req.model)
        if req.noise is None and gen is not None:
            io = self.models[req.model].model.io
            with self._noise_lock:
                state = gen.get_state()
                req.noise = torch.randn(io.horizon, io.action_dim, generator=gen).numpy()
                try:
                    self.queues.put(req)
                except ProtocolError:
                    gen.set_state(state)  # a refused request (OVERLOADED) leaves the noise sequence as it was
                    raise
            return
        self.queues.put(req)

    def prepare(self) -> None:
        """One-time start-up work (warm-up, graph capture) before serving."""

    def step(self) -> bool:
        """Run one scheduling step; False when there was nothing to do."""
        raise NotImplementedError

    def run(self, stop: threading.Event) -> None:
        self.queues.reopen()  # closed by the previous run's finish, if any
        while not stop.is_set():
            try:
                if not self.step():
                    self.queues.wait(0.005)
            except Exception:  # a fault in one batch must not stop the executor
                log.exception("engine step failed")
        self.finish()

    def finish(self) -> None:
        """Answer everything still queued at shutdown; later submits are refused (UNAVAILABLE)."""
        pending, shed = self.queues.close()
        self._emit(self._expired_results(shed)
                   + [Result(r, error=(ErrorCode.UNAVAILABLE, "executor is shutting down")) for r in pending])

    def _emit(self, results: list[Result]) -> None:
        """Hand results to the sink. Its fault (the I/O layer's) must neither stop the engine's loop nor lose the
        results handed over after it in the same step: a raise here took a batch's answers with it (and, in a
        lockstep, raised into its step between the launch and the end of its batches)."""
        if not results:
            return
        try:
            self.on_results(results)
        except Exception:
            log.exception("result sink failed")

    def _report_expired(self, expired: list[Request]) -> None:
        self._emit(self._expired_results(expired))

    def _expired_results(self, expired: list[Request]) -> list[Result]:
        """DEADLINE_EXCEEDED for requests the queues shed: late already, or too late to make it (shed_late)."""
        now = time.monotonic()
        estimates = {m: self.queues.service_estimate(m, now) for m in {r.model for r in expired}}  # once a model
        return [Result(r, error=(ErrorCode.DEADLINE_EXCEEDED, "deadline passed while queued" if r.deadline <= now
                                 else f"deadline cannot be met: {(r.deadline - now) * 1e3:.1f} ms left, recent "
                                      f"service time {estimates[r.model] * 1e3:.1f} ms"))
                for r in expired]


class MonolithicEngine(Engine):
    """VLM then action stage as one pipeline on one stream, one batch at a time (the baseline).

    On a GPU (``engine.graphs``, the default) it replays the same CUDA graphs as the lockstep
    engine (``GraphStages``: one per model, stage and batch size, over the same static
    buffers), back to back on one stream, so the comparison isolates the overlap of the two
    stages. On the CPU (or with ``graphs: false``) the stages run eagerly. Noise is drawn at
    submission like the lockstep engine's. Telemetry: one ``LockstepRecord`` per batch
    (both stages of the same batch, run serially: overlap 0).
    """

    def __init__(self, models, cfg, device, on_results):
        super().__init__(models, cfg, device, on_results)
        from services.executor.telemetry import Telemetry

        self.stages = {name: EagerStages(m.model, device, seed=cfg.seed) for name, m in models.items()}
        self.graphed: dict = {}  # name -> GraphStages on a GPU with graphs
        self.telemetry = Telemetry(path=cfg.telemetry_file)
        self._index = 0
        self._stream = None
        self._events = None

    def prepare(self) -> None:
        if self.device.type == "cuda" and self.cfg.graphs:
            self._prepare_graphs()
            return
        # One pass per batch size so allocator and kernel caches are warm before the first robot.
        b = 1
        while b <= self.cfg.max_batch:
            for st in self.stages.values():
                images, state, tokens = st.model.example_inputs(b, self.device)
                st.action(st.vlm(images, state, tokens), st.model.noise(b, self.device))
            b *= 2

    def _prepare_graphs(self) -> None:
        from services.executor.graphs import GraphPools, GraphStages

        torch.cuda.set_device(self.device)
        sizes = [1 << i for i in range(self.cfg.max_batch.bit_length()) if 1 << i <= self.cfg.max_batch]
        self._stream = torch.cuda.Stream(self.device)
        pools = GraphPools.create()
        for name, m in self.models.items():
            st = GraphStages(m.model, self.device, sizes, self.cfg.seed, pools, None, self._stream, self._stream)
            st.allocate()
            st.capture_action()
            for b in sizes:
                st.capture_vlm(b, {None})
            self.graphed[name] = st
        self._events = [torch.cuda.Event(enable_timing=True) for _ in range(3)]
        torch.cuda.synchronize(self.device)

    def step(self) -> bool:
        model, batch, expired = self.queues.take(self.cfg.max_batch)
        self._report_expired(expired)
        if not batch:
            return bool(expired)
        admitted = time.monotonic()
        try:
            if model in self.graphed:
                actions, vlm_ms, act_ms = self._run_graphs(self.graphed[model], batch)
                t_act = time.monotonic()
                t_vlm = admitted + vlm_ms / 1e3
            else:
                st = self.stages[model]
                images, state, tokens, noise = st.inputs(batch)
                handoff = st.vlm(images, state, tokens)
                _sync(self.device)
                t_vlm = time.monotonic()
                actions = st.action(handoff, noise).float().cpu().numpy()
                t_act = time.monotonic()
                vlm_ms, act_ms = (t_vlm - admitted) * 1e3, (t_act - t_vlm) * 1e3
            # In the try: rows missing from a model's output fail their batch here, answered, not the engine loop.
            results = [Result(r, actions=actions[i], admitted=admitted, vlm_s=t_vlm - admitted,
                              action_s=t_act - t_vlm, done=t_act, lockstep=self._index) for i, r in enumerate(batch)]
        except Exception as exc:
            log.exception("batch of %d for %s failed", len(batch), model)
            self._emit([Result(r, error=(ErrorCode.INTERNAL, f"inference failed: {type(exc).__name__}"))
                        for r in batch])
            return True
        self._emit(results)
        self._record(model, len(batch), admitted, vlm_ms, act_ms)
        return True

    def _run_graphs(self, st, batch: list[Request]):
        """Both stages' graphs back to back on the one stream; one wait at the end (CUDA events)."""
        b = len(batch)
        ev0, ev1, ev2 = self._events
        st.stage(b, batch)
        s = self._stream
        with torch.cuda.stream(s):
            ev0.record(s)
            st.vlm(b, None)
            ev1.record(s)
            st.handoff(b)
            st.action(b, 0)
            ev2.record(s)
        # While the GPU runs: copy the observations of the batch likely taken next (as the lockstep engine does).
        nxt_model, nxt = self.queues.peek(self.cfg.max_batch)
        if nxt and nxt_model in self.graphed:
            self.graphed[nxt_model].prestage(len(nxt), nxt)
        ev2.synchronize()
        return st.result(b, 0).copy(), ev0.elapsed_time(ev1), ev1.elapsed_time(ev2)

    def _record(self, model: str, b: int, start: float, vlm_ms: float, act_ms: float) -> None:
        from services.executor.telemetry import LockstepRecord

        arch = getattr(self.graphed.get(model), "arch", None) or self.models[model].model.arch
        self.telemetry.add(LockstepRecord(index=self._index, start=start, vlm_model=model, vlm_arch=arch, vlm_batch=b,
                                          action_model=model, action_arch=arch, action_batch=b, sm_level=None,
                                          duration_ms=vlm_ms + act_ms, vlm_ms=vlm_ms, action_ms=act_ms))
        self._index += 1

    def finish(self) -> None:
        try:
            super().finish()
        finally:
            self.telemetry.close()  # never raises: the file is best-effort


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


# The one list of engine kinds (shared/config.ENGINE_KINDS mirrors its keys and adds "auto", see
# resolve_kind). A kind is its class, or "module:Class" for engines built on this module
# (imported on first use: they import this module, so they cannot be imported here).
ENGINES: dict[str, type[Engine] | str] = {
    "monolithic": MonolithicEngine,
    "robion": "services.executor.lockstep:RobionEngine",
    "disagg": "services.executor.baselines.lockstep_variants:DisaggEngine",
    "static": "services.executor.baselines.lockstep_variants:StaticEngine",
    "disjoint": "services.executor.baselines.lockstep_variants:DisjointEngine",
    "procdisagg": "services.executor.baselines.procdisagg:ProcDisaggEngine",
    "interdisagg": "services.executor.baselines.interdisagg:InterDisaggEngine",
}


def resolve_kind(kind: str, device: torch.device) -> str:
    """The engine ``engine.kind`` runs on ``device``. ``auto`` (the default): robion on a GPU; monolithic on the
    CPU, which runs the two stages one after the other whatever the engine, so a lockstep there only makes each
    request wait for the next lockstep's action stage."""
    if kind != "auto":
        return kind
    return "robion" if device.type == "cuda" else "monolithic"


def engine_class(kind: str) -> type[Engine]:
    """The class behind ``engine.kind``, importing its module on first use."""
    if kind not in ENGINES:
        raise ValueError(f"engine {kind!r} is not available; available: {', '.join(ENGINES)}")
    entry = ENGINES[kind]
    if isinstance(entry, str):
        import importlib

        module, _, name = entry.partition(":")
        cls = getattr(importlib.import_module(module), name)
        # Importing the module may itself have registered the class (lockstep.py does).
        ENGINES[kind] = entry = cls
    return entry


def make_engine(models: dict[str, ServedModel], cfg: EngineConfig, device: torch.device, on_results: ResultSink) -> Engine:
    return engine_class(resolve_kind(cfg.kind, device))(models, cfg, device, on_results)
