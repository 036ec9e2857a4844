"""Inter-GPU stage disaggregation, ``engine.kind: interdisagg`` (paper experiment 8).

The cluster design Robion's intra-GPU overlap is compared with: some GPUs run only the VLM
stage, the others only the action stage (Dis-a:b = a VLM GPUs, b action GPUs). One
process, one thread per stage worker; each worker owns one device and a replica of every
served model on it.

```
queues (shared, policy) ─take─▶ VLM worker i (vlm_devices[i]): stage, H2D, VLM graph(b)
      ─pick the action worker with the fewest pending batches, take a free receive slot on its device─
      ─copy the handoff (KV cache + noise, one flat buffer) device to device (peer-to-peer where
       the GPUs allow it), wait for it─▶ action worker j (action_devices[j]) inbox
action worker j: slot ─local copy─▶ act_in ─action graph(b)─▶ pinned output ─▶ on_results
```

- **Batches** come from the engine's one set of queues with the configured policy (``take``
  up to ``max_batch``, power-of-two sizes), so every VLM worker competes for the same
  requests and expired heads are shed there as in every engine. A batch stays a batch: the
  action worker runs it with the action graph of its size (no regrouping across VLM workers).
- **Handoff**: each action worker has ``handoff_slots`` receive buffers per (model, batch
  size) on its device. A VLM worker takes a free slot (waiting when every action worker is
  full: back-pressure), copies its ``vlm_out`` into it on its own stream and waits for the
  copy, then hands the slot over; the action worker returns it after its action stage ended.
  The slot is what lets the next VLM batch be copied while the action worker still runs.
- **Timings** (Result): ``admitted`` when the batch was taken from the queue, ``vlm_s`` up to
  the handoff being on the action device, ``action_s`` from then to the actions on the host
  (the wait in the action worker's inbox included), ``done`` at that point.
- **Graphs**: on a GPU with ``engine.graphs`` each worker replays CUDA graphs (VLM graphs per
  batch size on VLM workers, action graphs per batch size on action workers; ``GraphStages``,
  one memory pool pair per worker, since workers on one device may run at the same time);
  eager otherwise (the CPU).
- **Shutdown** (``finish``): VLM workers stop taking batches and finish the one they hold,
  everything still queued is answered ``UNAVAILABLE``, then the action workers finish every
  handed-off batch (those robots get real actions) and exit.

Every worker drives its device from Python, so all of them share one GIL: the launch cost of
a graph is small, but this is one process for the whole cluster, unlike executors in
deployment (one process per GPU).
"""

from __future__ import annotations

import copy
import itertools
import logging
import queue
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from services.executor.baselines.procdisagg import StepTelemetry
from services.executor.engine import Engine, ResultSink, ServedModel
from services.executor.scheduler import Request, Result
from services.executor.stages import BufferedStages, Pack
from shared.config import EngineConfig, parse_devices
from shared.models.base import VLAModel
from shared.protocol import ErrorCode

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- telemetry

@dataclass
class BatchRecord:
    """One batch through both stages."""

    index: int
    start: float  # time.monotonic() when the batch was taken from the queue
    model: str
    batch: int
    vlm_worker: int
    action_worker: int
    vlm_ms: float  # VLM stage (device time on a GPU, host time on the CPU)
    handoff_ms: float  # copy of the handoff to the action worker's device
    wait_ms: float  # handoff ready -> action worker started it (its inbox)
    action_ms: float

    # Names the capacity harness's telemetry summary reads from lockstep records.
    @property
    def vlm_batch(self) -> int:
        return self.batch

    @property
    def action_batch(self) -> int:
        return self.batch

    @property
    def sm_level(self) -> None:
        return None


class BatchTelemetry(StepTelemetry):
    """The ring of ``BatchRecord``s (procdisagg's ring, this engine's summary)."""

    def summary(self) -> dict:
        recs = self.records()

        def pct(key: str) -> dict:
            xs = [getattr(r, key) for r in recs]
            return {"median": float(np.median(xs)) if xs else None, "p99": float(np.percentile(xs, 99)) if xs else None}

        return {"batches": len(recs), "mean_batch": float(np.mean([r.batch for r in recs])) if recs else None,
                "per_vlm_worker": _counts(r.vlm_worker for r in recs),
                "per_action_worker": _counts(r.action_worker for r in recs),
                "vlm_ms": pct("vlm_ms"), "handoff_ms": pct("handoff_ms"), "wait_ms": pct("wait_ms"),
                "action_ms": pct("action_ms")}


def _counts(xs) -> dict[str, int]:
    out: dict[str, int] = {}
    for x in xs:
        out[str(x)] = out.get(str(x), 0) + 1
    return out


# ----------------------------------------------------------------------------- workers

def replicate(model: VLAModel, device: torch.device) -> VLAModel:
    """A copy of ``model`` on ``device`` (the model itself when it is there already).

    Parameters and buffers are copied straight to the target device (deepcopy's memo), so the
    source device never holds a second copy of the weights.
    """
    first = next(itertools.chain(model.parameters(), model.buffers()), None)
    if first is None or first.device == device:
        return model
    memo: dict[int, object] = {}
    for t in itertools.chain(model.parameters(), model.buffers()):
        memo[id(t)] = (nn.Parameter(t.detach().to(device), requires_grad=t.requires_grad)
                       if isinstance(t, nn.Parameter) else t.to(device))
    return copy.deepcopy(model, memo).to(device)


@dataclass
class _Worker:
    role: str  # "vlm" or "action"
    index: int
    device: torch.device
    stages: dict[str, BufferedStages] = field(default_factory=dict)  # model name -> its stages on this device
    stream: object = None  # torch.cuda.Stream on a GPU
    events: list = field(default_factory=list)  # timing events (GPU)
    thread: threading.Thread | None = None
    # Action workers only:
    inbox: queue.Queue = field(default_factory=queue.Queue)
    ring: dict[tuple[str, int], list[Pack]] = field(default_factory=dict)  # receive slots per (model, batch)
    free: dict[tuple[str, int], list[int]] = field(default_factory=dict)
    pending: int = 0  # batches handed to it (or about to be) and not finished
    assigned: int = 0  # batches ever handed to it (spreads ties)

    @property
    def cuda(self) -> bool:
        return self.device.type == "cuda"

    def stream_ctx(self):
        return torch.cuda.stream(self.stream) if self.cuda else _NullCtx()


class _NullCtx:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


@dataclass
class _Handoff:
    """A batch past its VLM stage, waiting in an action worker's inbox."""

    model: str
    b: int
    batch: list[Request]
    slot: int
    admitted: float
    vlm_end: float
    vlm_worker: int
    vlm_ms: float
    handoff_ms: float


# ----------------------------------------------------------------------------- engine

class InterDisaggEngine(Engine):
    """``engine.kind: interdisagg``: VLM workers on some devices, action workers on others."""

    def __init__(self, models: dict[str, ServedModel], cfg: EngineConfig, device: torch.device, on_results: ResultSink):
        super().__init__(models, cfg, device, on_results)
        try:
            vlm = parse_devices(cfg.vlm_devices, required=True)
        except ValueError as exc:
            raise ValueError(f"engine.vlm_devices: {exc}") from None
        try:
            act = parse_devices(cfg.action_devices, required=True)
        except ValueError as exc:
            raise ValueError(f"engine.action_devices: {exc}") from None
        self.vlm_workers = [_Worker("vlm", i, torch.device(d)) for i, d in enumerate(vlm)]
        self.action_workers = [_Worker("action", j, torch.device(d)) for j, d in enumerate(act)]
        self.telemetry = BatchTelemetry()
        self.peer_access: dict[str, bool] = {}
        self._slots_cv = threading.Condition()
        self._stop_vlm = threading.Event()
        self._running = False
        self._index = itertools.count()

    # ------------------------------------------------------------------ start-up

    def prepare(self) -> None:
        # Start-up makes each worker's device current in turn; the caller's thread gets its
        # own back (its later kernels, e.g. Triton launches, go to the current device).
        previous = torch.cuda.current_device() if any(w.cuda for w in self.vlm_workers + self.action_workers) else None
        try:
            self._prepare()
        finally:
            if previous is not None:
                torch.cuda.set_device(previous)

    def _prepare(self) -> None:
        from services.executor.lockstep import batch_sizes

        sizes = batch_sizes(self.cfg.max_batch)
        workers = self.vlm_workers + self.action_workers
        replicas: dict[torch.device, dict[str, VLAModel]] = {}
        for w in workers:
            if w.device not in replicas:
                if w.cuda:
                    torch.cuda.set_device(w.device)
                replicas[w.device] = {name: replicate(m.model, w.device) for name, m in self.models.items()}
        graphs = self.cfg.graphs
        for w in workers:
            if w.cuda:
                torch.cuda.set_device(w.device)
                w.stream = torch.cuda.Stream(w.device)
                w.events = [torch.cuda.Event(enable_timing=True) for _ in range(4)]
                pools = None
                if graphs:
                    from services.executor.graphs import GraphPools

                    pools = GraphPools.create()  # per worker: two workers of one device may replay at once
            for name in self.models:
                model = replicas[w.device][name]
                if w.cuda and graphs:
                    from services.executor.graphs import GraphStages

                    st = GraphStages(model, w.device, sizes, self.cfg.seed, pools, None, w.stream, w.stream)
                else:
                    st = BufferedStages(model, w.device, sizes, self.cfg.seed)
                with w.stream_ctx():
                    st.allocate()
                    if w.role == "vlm":
                        for b in sizes:
                            st.capture_vlm(b, {None})
                    elif w.cuda and graphs:
                        st.capture_action()
                    else:
                        for b in sizes:  # warm the eager action stage (allocator, kernel caches)
                            st.action(b, 0)
                w.stages[name] = st
                if w.role == "action":
                    for b in sizes:
                        specs = {k: (tuple(v.shape), v.dtype) for k, v in st.vlm_out[b].views.items()}
                        w.ring[(name, b)] = [Pack.allocate(specs, w.device) for _ in range(self.cfg.handoff_slots)]
                        w.free[(name, b)] = list(range(self.cfg.handoff_slots))
        # One copy per (VLM worker, action worker) pair: enables peer access and maps the
        # buffers now, not on the first robot's request.
        for v, a in itertools.product(self.vlm_workers, self.action_workers):
            if v.cuda and a.cuda and v.device != a.device:
                self.peer_access[f"{v.device}->{a.device}"] = torch.cuda.can_device_access_peer(v.device, a.device)
            for name in self.models:
                for b in sizes:
                    with v.stream_ctx():
                        a.ring[(name, b)][0].flat.copy_(v.stages[name].vlm_out[b].flat, non_blocking=True)
        for w in workers:
            if w.cuda:
                torch.cuda.synchronize(w.device)
        log.info("interdisagg: VLM workers on %s, action workers on %s (%s)",
                 [str(w.device) for w in self.vlm_workers], [str(w.device) for w in self.action_workers],
                 "CUDA graphs" if graphs and any(w.cuda for w in workers) else "eager")

    # ------------------------------------------------------------------ serving

    def run(self, stop: threading.Event) -> None:
        self.queues.reopen()  # closed by the previous run's finish, if any
        self._start()
        stop.wait()
        self.finish()

    def _start(self) -> None:
        self._stop_vlm.clear()
        for w in self.vlm_workers:
            w.thread = threading.Thread(target=self._vlm_loop, args=(w,), name=f"interdisagg-vlm{w.index}", daemon=True)
        for w in self.action_workers:
            w.inbox = queue.Queue()
            w.thread = threading.Thread(target=self._action_loop, args=(w,), name=f"interdisagg-action{w.index}",
                                        daemon=True)
        self._running = True
        for w in self.vlm_workers + self.action_workers:
            w.thread.start()

    def finish(self) -> None:
        """VLM workers stop taking batches; the queued are answered UNAVAILABLE; handed-off batches complete."""
        if self._running:
            self._stop_vlm.set()
            self._join(self.vlm_workers)
        super().finish()
        if self._running:
            for w in self.action_workers:
                w.inbox.put(None)  # after every handoff of the stopped VLM workers
            self._join(self.action_workers)
            self._running = False

    @staticmethod
    def _join(workers: list[_Worker], timeout_s: float = 60.0) -> None:
        for w in workers:
            if w.thread is not None:
                w.thread.join(timeout_s)
                if w.thread.is_alive():
                    log.error("interdisagg %s worker %d did not stop within %.0f s", w.role, w.index, timeout_s)

    def _fail(self, batch: list[Request], exc: Exception) -> None:
        self._emit([Result(r, error=(ErrorCode.INTERNAL, f"inference failed: {type(exc).__name__}")) for r in batch])

    # VLM side ---------------------------------------------------------

    def _vlm_loop(self, w: _Worker) -> None:
        if w.cuda:
            torch.cuda.set_device(w.device)
        while not self._stop_vlm.is_set():
            try:
                model, batch, expired = self.queues.take(self.cfg.max_batch)
                self._report_expired(expired)
            except Exception:
                log.exception("interdisagg: taking a batch failed")
                continue
            if not batch:
                self.queues.wait(0.005)
                continue
            self._run_vlm(w, model, batch)

    def _run_vlm(self, w: _Worker, model: str, batch: list[Request]) -> None:
        admitted = time.monotonic()
        b = len(batch)
        st = w.stages[model]
        target: tuple[_Worker, int] | None = None
        try:
            st.stage(b, batch)
            with w.stream_ctx():
                if w.cuda:
                    w.events[0].record(w.stream)
                st.vlm(b, None)
                if w.cuda:
                    w.events[1].record(w.stream)
            t_vlm = time.monotonic()
            # Chosen while the VLM stage runs on the device; may wait for a free slot (back-pressure).
            target = self._acquire(model, b)
            a, slot = target
            t_copy = time.monotonic()  # the handoff's time is its copy's, not the wait for a slot before it
            with w.stream_ctx():
                if w.cuda:
                    w.events[3].record(w.stream)
                # On the VLM worker's stream: the next VLM batch cannot overwrite vlm_out before
                # the copy read it. Cross-device, torch copies peer-to-peer where enabled.
                a.ring[(model, b)][slot].flat.copy_(st.vlm_out[b].flat, non_blocking=True)
                if w.cuda:
                    w.events[2].record(w.stream)
            if w.cuda:
                w.events[2].synchronize()
                vlm_ms = w.events[0].elapsed_time(w.events[1])
                handoff_ms = w.events[3].elapsed_time(w.events[2])
            else:
                vlm_ms, handoff_ms = (t_vlm - admitted) * 1e3, (time.monotonic() - t_copy) * 1e3
            vlm_end = time.monotonic()
        except Exception as exc:
            log.exception("interdisagg: VLM batch of %d for %s failed", b, model)
            if target is not None:
                self._release(target[0], model, b, target[1])
            self._fail(batch, exc)
            return
        a.inbox.put(_Handoff(model, b, batch, slot, admitted, vlm_end, w.index, vlm_ms, handoff_ms))

    def _acquire(self, model: str, b: int) -> tuple[_Worker, int]:
        """The action worker with the fewest pending batches among those with a free slot, and the slot."""
        key = (model, b)
        with self._slots_cv:
            while True:
                ready = [a for a in self.action_workers if a.free[key]]
                if ready:
                    a = min(ready, key=lambda x: (x.pending, x.assigned, x.index))
                    a.pending += 1
                    a.assigned += 1
                    return a, a.free[key].pop()
                self._slots_cv.wait(0.05)

    def _release(self, a: _Worker, model: str, b: int, slot: int) -> None:
        with self._slots_cv:
            a.free[(model, b)].append(slot)
            a.pending -= 1
            self._slots_cv.notify_all()

    # action side ------------------------------------------------------

    def _action_loop(self, a: _Worker) -> None:
        if a.cuda:
            torch.cuda.set_device(a.device)
        while True:
            h = a.inbox.get()
            if h is None:
                return
            self._run_action(a, h)

    def _run_action(self, a: _Worker, h: _Handoff) -> None:
        st = a.stages[h.model]
        b = h.b
        started = time.monotonic()
        try:
            with a.stream_ctx():
                if a.cuda:
                    a.events[0].record(a.stream)
                st.act_in[b].flat.copy_(a.ring[(h.model, b)][h.slot].flat, non_blocking=True)
                st.action(b, 0)  # action stage, then its output to pinned host memory
                if a.cuda:
                    a.events[1].record(a.stream)
            if a.cuda:
                a.events[1].synchronize()
                action_ms = a.events[0].elapsed_time(a.events[1])
            done = time.monotonic()
            if not a.cuda:
                action_ms = (done - started) * 1e3
            actions = st.result(b, 0).copy()
        except Exception as exc:
            log.exception("interdisagg: action batch of %d for %s failed", b, h.model)
            self._release(a, h.model, b, h.slot)
            self._fail(h.batch, exc)
            return
        self._release(a, h.model, b, h.slot)
        self._emit([Result(r, actions=actions[i], admitted=h.admitted, vlm_s=h.vlm_end - h.admitted,
                           action_s=done - h.vlm_end, done=done) for i, r in enumerate(h.batch)])
        self.telemetry.add([BatchRecord(next(self._index), h.admitted, h.model, b, h.vlm_worker, a.index, h.vlm_ms,
                                        h.handoff_ms, (started - h.vlm_end) * 1e3, action_ms)])
