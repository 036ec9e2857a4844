"""The process-disaggregated engine (the vLLM-Omni design), ``engine.kind: procdisagg``.

Three parties on one GPU:

- the **front** (this engine object, in the caller's process) owns the per-model queues
  and the scheduling policy, forms VLM batches (up to ``max_batch``, power-of-two sizes)
  and writes their observations and noise into shared host memory (a ring of input slots,
  two per model);
- the **VLM process** copies a batch to the device, replays the VLM stage's CUDA graph for
  that batch size, and writes each request's handoff (KV cache / hidden states + noise)
  into the **inter-stage buffer**: a device ring of handoff slots allocated once by the
  front and mapped into both stage processes through CUDA IPC (``torch.multiprocessing``
  shares the storage); it then sends the slot's index and the request numbers over a
  small control channel (a ``multiprocessing`` queue);
- the **action process** runs a continuous batch: before *every* denoising step it
  checks the control channel for arrived handoffs, merges them into its running batch
  (their per-request state is built from the slot and copied into the batch's static
  rows), runs one denoising step for every row (rows at different steps advance together:
  ``stepping.py`` gives each zoo model a per-step form), and lets finished requests leave
  (their actions go back to the front, the running batch is compacted). One CUDA graph
  per running-batch size replays the step; admission and compaction are eager copies.

The handoff slots go back to the VLM process once their requests were admitted (a free
list on another queue), so a full action side back-pressures the VLM side. Results carry
stage timings; ``done`` is the time the action process saw the actions on the host.

Telemetry: one ``StepRecord`` per denoising step of the action process (running batch,
per-row step indices, arrivals merged, requests finished, GPU time of the step, host time
spent inspecting and packing), kept by the front in ``engine.telemetry``.

On the CPU the same three parties run as processes too (shared memory instead of CUDA
IPC) with eager stages; ``procdisagg_workers: thread`` runs the two stages as threads of
the caller's process instead (same code and channels, no IPC).
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing as std_mp
import queue as std_queue
import threading
import time
import weakref
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from services.executor.engine import Engine, ResultSink, ServedModel
from services.executor.scheduler import Request, Result
from services.executor.stages import NOISE, Pack
from shared.config import EngineConfig
from shared.protocol import ErrorCode

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- telemetry

@dataclass
class StepRecord:
    """One denoising step of the action process."""

    index: int
    start: float  # time.monotonic() when the step was launched
    model: str
    batch: int  # rows in the step
    row_steps: list[int]  # each row's step index before this step (several values: requests at different steps)
    admitted: int  # requests merged into the running batch just before this step
    finished: int  # requests that left after this step
    step_ms: float | None  # GPU time of the step graph (admission copies before it excluded); None when not measured
    inspect_us: float  # host time checking the channel and packing arrivals before this step

    # Names the capacity harness's telemetry summary reads from lockstep records.
    @property
    def vlm_batch(self) -> int:
        return 0

    @property
    def action_batch(self) -> int:
        return self.batch

    @property
    def sm_level(self) -> None:
        return None


class StepTelemetry:
    def __init__(self, capacity: int = 16384):
        self._ring: deque[StepRecord] = deque(maxlen=capacity)
        self._lock = threading.Lock()
        self.count = 0

    def add(self, recs: list[StepRecord]) -> None:
        with self._lock:
            self._ring.extend(recs)
            self.count += len(recs)

    def records(self) -> list[StepRecord]:
        with self._lock:
            return list(self._ring)

    def clear(self) -> None:
        with self._lock:
            self._ring.clear()

    def summary(self) -> dict:
        recs = self.records()
        timed = [r.step_ms for r in recs if r.step_ms is not None]
        return {
            "steps": len(recs),
            "mean_batch": float(np.mean([r.batch for r in recs])) if recs else None,
            "merges": sum(1 for r in recs if r.admitted and r.batch > r.admitted),
            "mixed_steps": sum(1 for r in recs if len(set(r.row_steps)) > 1),
            "mean_step_ms": float(np.mean(timed)) if timed else None,
            "inspect_us": {"median": float(np.median([r.inspect_us for r in recs])) if recs else None,
                           "p99": float(np.percentile([r.inspect_us for r in recs], 99)) if recs else None},
        }


# ----------------------------------------------------------------------------- shared layout

@dataclass
class _ModelPlan:
    """What both stage processes need to know about one served model (picklable)."""

    name: str
    model: Any  # the VLAModel (weights shared through CUDA IPC / shared memory)
    in_flat: torch.Tensor  # the host shared-memory input slot (flat uint8) the front fills with a batch
    in_specs: dict  # name -> (shape, dtype) of one slot at max_batch
    ring_flat: torch.Tensor  # device handoff ring (flat uint8): groups x max_batch requests
    ring_specs: dict  # name -> (shape, dtype) of the whole ring (dim 0: groups * max_batch)
    groups: int


def _views(flat: torch.Tensor, specs: dict) -> dict[str, torch.Tensor]:
    """The typed views ``Pack.allocate`` lays out over ``flat`` (same order, same alignment)."""
    import math

    from services.executor.stages import _align

    out, off = {}, 0
    for name, (shape, dtype) in specs.items():
        n = math.prod(shape) * dtype.itemsize
        out[name] = flat[off:off + n].view(dtype).view(shape)
        off = _align(off + n)
    return out


@dataclass
class _Shared:
    device: str
    max_batch: int
    running: int
    seed: int
    graphs: bool
    plans: list[_ModelPlan]


@dataclass
class _Obs:
    """A request as the VLM side's staging code reads it (views into an input slot)."""

    images: np.ndarray
    state: np.ndarray
    tokens: np.ndarray
    noise: np.ndarray


# ----------------------------------------------------------------------------- VLM process

def vlm_worker(shared: _Shared, inbox, to_action, free_groups, vlm_ready, results) -> None:
    """Batches from the front -> VLM graph -> handoff slots -> control message to the action process."""
    try:
        _vlm_loop(shared, inbox, to_action, free_groups, vlm_ready, results)
    except Exception as exc:  # a dead stage must not leave the front waiting forever
        log.exception("VLM process failed")
        results.put(("fatal", f"VLM process: {type(exc).__name__}: {exc}"))


@torch.no_grad()
def _vlm_loop(shared: _Shared, inbox, to_action, free_groups, vlm_ready, results) -> None:
    from services.executor.lockstep import batch_sizes
    from services.executor.stages import BufferedStages

    device = torch.device(shared.device)
    cuda = device.type == "cuda"
    sizes = batch_sizes(shared.max_batch)
    stream = None
    if cuda:
        torch.cuda.set_device(device)
        stream = torch.cuda.Stream(device)
    stages, ring, inputs, free = [], [], [], []
    for p in shared.plans:
        if cuda and shared.graphs:
            from services.executor.graphs import GraphStages

            st = GraphStages(p.model, device, sizes, shared.seed, _vlm_worker_pools(), None, stream, stream)
        else:
            st = BufferedStages(p.model, device, sizes, shared.seed)
        st.allocate()
        if cuda and shared.graphs:
            for b in sizes:
                st.capture_vlm(b, {None})
        stages.append(st)
        ring.append(_views(p.ring_flat, p.ring_specs))
        inputs.append(_views(p.in_flat, p.in_specs))
        free.append(deque(range(p.groups)))
    if cuda:
        torch.cuda.synchronize(device)
    done_ev = torch.cuda.Event() if cuda else None
    results.put(("ready", "vlm"))
    while True:
        msg = inbox.get()
        if msg is None:
            to_action.put(None)
            return
        mi, seqs, admitted = msg
        b = len(seqs)
        p, st = shared.plans[mi], stages[mi]
        g = None  # given back on failure: kept, it would stall this model for good
        try:
            np_in = {k: t.numpy() for k, t in inputs[mi].items()}
            st.stage(b, [_Obs(np_in["images"][i], np_in["state"][i], np_in["tokens"][i], np_in[NOISE][i])
                         for i in range(b)])
            while not free[mi]:  # back-pressure: wait for the action process to release a group
                free[mi].append(free_groups[mi].get())
            while True:  # collect any other released groups without waiting
                try:
                    free[mi].append(free_groups[mi].get_nowait())
                except std_queue.Empty:
                    break
            g = free[mi].popleft()
            row = g * shared.max_batch
            if cuda:
                with torch.cuda.stream(stream):
                    st.vlm(b, None)
                    out = st.vlm_out[b].views
                    for k, t in ring[mi].items():
                        t[row:row + b].copy_(out[k])
                    done_ev.record(stream)
                done_ev.synchronize()
            else:
                st.vlm(b, None)
                out = st.vlm_out[b].views
                for k, t in ring[mi].items():
                    t[row:row + b].copy_(out[k])
            t_end = time.monotonic()
        except Exception as exc:
            log.exception("VLM batch failed")
            if g is not None:  # never sent to the action process: free again for the next batch
                free[mi].appendleft(g)
            results.put(("error", seqs, f"inference failed: {type(exc).__name__}"))
        else:
            to_action.put((mi, g, seqs, admitted, t_end))
        # Ready for the next batch, which the front forms now from what is queued then, as a vLLM engine's scheduler
        # forms each step's batch when the step is about to run. A batch formed while this one still ran would be
        # formed early (smaller, and past shedding when it turns late) and wait a whole VLM run in its slot.
        vlm_ready.put(mi)


_POOLS = None


def _vlm_worker_pools():
    global _POOLS
    if _POOLS is None:
        from services.executor.graphs import GraphPools

        _POOLS = GraphPools.create()
    return _POOLS


# ----------------------------------------------------------------------------- action process

@dataclass
class _Running:
    """One model's continuous batch in the action process."""

    adapter: Any
    state: dict  # static rows [running, ...]
    graphs: dict  # n -> CUDA graph of one step over rows [:n]
    seqs: list = field(default_factory=list)  # per row: (seq, admitted, vlm_end)
    steps: list = field(default_factory=list)  # per row: steps done (host mirror of state["step"])
    pending: deque = field(default_factory=deque)  # arrived handoff messages not yet admitted


def action_worker(shared: _Shared, inbox, free_groups, results) -> None:
    try:
        _action_loop(shared, inbox, free_groups, results)
    except Exception as exc:
        log.exception("action process failed")
        results.put(("fatal", f"action process: {type(exc).__name__}: {exc}"))


def _capture_step(ad, S: dict, n: int, stream, pool):
    view = ad.view(S, n)
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):
        for _ in range(2):  # warm-up (cuBLAS workspaces, autotuning); step indices kept in range
            view["step"].zero_()
            ad.step(view, n)
        view["step"].zero_()
    stream.synchronize()
    g = torch.cuda.CUDAGraph()
    with torch.cuda.graph(g, pool=pool, stream=stream):
        ad.step(view, n)
    stream.synchronize()
    return g


@torch.no_grad()
def _action_loop(shared: _Shared, inbox, free_groups, results) -> None:
    from services.executor.baselines.stepping import step_adapter

    device = torch.device(shared.device)
    cuda = device.type == "cuda"
    stream = None
    if cuda:
        torch.cuda.set_device(device)
        stream = torch.cuda.Stream(device)
    graphs_on = cuda and shared.graphs
    pool = torch.cuda.graph_pool_handle() if graphs_on else None
    runs: list[_Running] = []
    rings = []
    for p in shared.plans:
        ad = step_adapter(p.model)
        if ad is None:
            raise RuntimeError(f"{p.name}: architecture {p.model.arch!r} has no per-step form (stepping.py)")
        ring = _views(p.ring_flat, p.ring_specs)
        rings.append(ring)
        example = {k: v[:1] for k, v in ring.items() if k != NOISE}
        S = ad.allocate(example, ring[NOISE][:1].to(ad.dtype), shared.running)
        graphs = {}
        if graphs_on:
            for n in range(1, shared.running + 1):
                graphs[n] = _capture_step(ad, S, n, stream, pool)
            for v in S.values():
                v.zero_()
        runs.append(_Running(ad, S, graphs))
    if cuda:
        torch.cuda.synchronize(device)
        ev_ring = [(torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)) for _ in range(64)]
    host_out = [torch.zeros(shared.running, p.model.io.horizon, p.model.io.action_dim, dtype=torch.float32,
                            pin_memory=cuda) for p in shared.plans]
    results.put(("ready", "action"))
    index = 0
    stopping = False
    unreported: list[tuple[StepRecord, Any]] = []  # records whose GPU time is read at the next sync

    def poll(block: bool) -> bool:
        """Check the control channel; True when the stop sentinel arrived."""
        nonlocal stopping
        while True:
            try:
                msg = inbox.get(timeout=0.05) if block else inbox.get_nowait()
            except std_queue.Empty:
                return stopping
            block = False
            if msg is None:
                stopping = True
                continue
            runs[msg[0]].pending.append(msg)

    while True:
        idle = all(not r.seqs and not r.pending for r in runs)
        if idle and stopping:
            results.put(("stopped",))
            return
        if idle:  # nothing to step: wait for the channel (not counted as inspection)
            poll(block=True)
            continue
        t_poll = time.perf_counter()
        poll(block=False)
        poll_s = time.perf_counter() - t_poll  # the channel's poll is shared by the models of this round
        for mi, run in enumerate(runs):
            if not run.seqs and not run.pending:
                continue
            # Each model's inspection from here, not from the round's start: a later model's would include the
            # earlier models' denoising steps (and, on a GPU, their synchronisation).
            t_inspect = time.perf_counter() - poll_s
            p, ad, S = shared.plans[mi], run.adapter, run.state
            ring = rings[mi]
            admitted = 0
            released = []
            ctx = torch.cuda.stream(stream) if cuda else _nullctx()
            with ctx:
                # Merge arrivals into the running batch (whole handoff groups, FIFO, while rows are free).
                while run.pending and len(run.seqs) + len(run.pending[0][2]) <= shared.running:
                    _, g, seqs, t_adm, t_vlm = run.pending.popleft()
                    b, at, row = len(seqs), len(run.seqs), g * shared.max_batch
                    ad.admit(S, at, {k: v[row:row + b] for k, v in ring.items() if k != NOISE},
                             ring[NOISE][row:row + b])
                    run.seqs += [(s, t_adm, t_vlm) for s in seqs]
                    run.steps += [0] * b
                    admitted += b
                    released.append(g)
                n = len(run.seqs)
                inspect_us = (time.perf_counter() - t_inspect) * 1e6
                rec = StepRecord(index, time.monotonic(), p.name, n, list(run.steps), admitted, 0, None, inspect_us)
                index += 1
                if cuda:
                    e0, e1 = ev_ring[index % len(ev_ring)]
                    e0.record(stream)
                if graphs_on:
                    run.graphs[n].replay()
                else:
                    ad.run(S, n)
                run.steps = [s + 1 for s in run.steps]
                done = [i for i, s in enumerate(run.steps) if s >= ad.steps]
                if cuda:
                    e1.record(stream)
                    unreported.append((rec, (e0, e1)))
                else:
                    unreported.append((rec, None))
                rec.finished = len(done)
                out = None
                if done:
                    idx = torch.tensor(done, dtype=torch.long, device=device)
                    out = host_out[mi][:len(done)]
                    out.copy_(ad.actions(S, idx), non_blocking=cuda)
                    keep = [i for i in range(n) if i not in set(done)]
                    # Compact: surviving rows beyond the new end move into the holes.
                    new_n = len(keep)
                    movers = [i for i in keep if i >= new_n]
                    holes = [i for i in range(new_n) if i in set(done)]
                    if movers:
                        ad.move(S, torch.tensor(movers, dtype=torch.long, device=device),
                                torch.tensor(holes, dtype=torch.long, device=device))
                    finished = [run.seqs[i] for i in done]
                    order = list(range(n))
                    for src, dst in zip(movers, holes):
                        order[dst] = src
                    run.seqs = [run.seqs[order[i]] for i in range(new_n)]
                    run.steps = [run.steps[order[i]] for i in range(new_n)]
            if done or released:
                if cuda:
                    stream.synchronize()
                t_done = time.monotonic()
                for g in released:
                    free_groups[mi].put(g)
                if done:
                    actions = out.numpy().copy()
                    results.put(("done", [(s, t_adm, t_vlm, t_done, actions[i])
                                          for i, (s, t_adm, t_vlm) in enumerate(finished)]))
                if cuda:
                    recs = []
                    for r, evs in unreported:
                        if evs is not None:
                            r.step_ms = evs[0].elapsed_time(evs[1])
                        recs.append(r)
                else:
                    recs = [r for r, _ in unreported]
                unreported = []
                results.put(("telemetry", recs))


class _nullctx:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


# ----------------------------------------------------------------------------- front

def _receive_loop(ref, results, stop: threading.Event) -> None:
    while not stop.is_set():
        try:
            msg = results.get(timeout=0.1)
        except std_queue.Empty:
            engine = ref()
            if engine is None:
                return
            # A stage killed from outside (the OOM killer, a signal) reports nothing: its requests would wait until
            # shutdown, and a start-up would wait out its whole timeout. Its exit is the report.
            dead = next((p for p in engine._procs if not p.is_alive()), None)  # noqa: SLF001
            if dead is not None and engine._fatal is None and not stop.is_set():  # noqa: SLF001
                engine._handle(("fatal", f"{dead.name} exited (code {getattr(dead, 'exitcode', None)})"))  # noqa: SLF001
            del engine
            continue
        except (EOFError, OSError, ValueError):
            return
        engine = ref()
        if engine is None:
            return
        try:
            engine._handle(msg)  # noqa: SLF001
        except Exception:
            log.exception("procdisagg: could not handle %s", msg[0])
        del engine


def _stop_workers(procs: list, inbox, results_thread_stop: threading.Event) -> None:
    results_thread_stop.set()
    try:
        inbox.put(None)
    except Exception:  # the queue may already be closed at interpreter exit
        pass
    for p in procs:
        p.join(timeout=10)
        if p.is_alive() and hasattr(p, "terminate"):
            p.terminate()  # e.g. the VLM process blocked on a handoff group its dead action process never frees
            p.join(timeout=5)


class ProcDisaggEngine(Engine):
    """``engine.kind: procdisagg``: VLM and action stages in two processes, continuous action batching."""

    def __init__(self, models: dict[str, ServedModel], cfg: EngineConfig, device: torch.device, on_results: ResultSink):
        super().__init__(models, cfg, device, on_results)
        self.names = list(models)
        self.running = cfg.running_batch or 4 * cfg.max_batch
        self.telemetry = StepTelemetry()
        self.vlm_ms: deque[float] = deque(maxlen=4096)
        self._inflight: dict[int, Request] = {}
        self._inflight_lock = threading.Lock()
        self._drained = threading.Condition(self._inflight_lock)
        self._seq = 0
        self._vlm_ready = True  # the VLM process waits for a batch (the front forms one only then)
        self._procs: list = []
        self._fatal: str | None = None
        self._ready: set[str] = set()
        self._ready_cv = threading.Condition()

    # ------------------------------------------------------------------ start-up

    def prepare(self) -> None:
        from services.executor.baselines.stepping import step_adapter
        from services.executor.stages import BufferedStages

        mode = self.cfg.procdisagg_workers
        cuda = self.device.type == "cuda"
        if cuda:
            torch.cuda.set_device(self.device)
        mb = self.cfg.max_batch
        groups = self.cfg.handoff_slots
        plans = []
        self._inputs = []
        for name, m in self.models.items():
            if step_adapter(m.model) is None:
                raise ValueError(f"procdisagg: {name} ({m.model.arch}) has no per-step action form in stepping.py")
            in_specs = BufferedStages(m.model, self.device, [1]).input_specs(mb)
            with torch.no_grad():  # the handoff's real layout (what the VLM stage writes)
                h1 = m.model.vlm_stage(*m.model.example_inputs(1, self.device))
            ring_specs = {k: ((groups * mb, *v.shape[1:]), v.dtype) for k, v in h1.items()}
            ring_specs[NOISE] = ((groups * mb, m.model.io.horizon, m.model.io.action_dim), torch.float32)
            in_flat = Pack.allocate(in_specs, torch.device("cpu")).flat.share_memory_()
            ring = Pack.allocate(ring_specs, self.device)
            plans.append(_ModelPlan(name, m.model, in_flat, in_specs, ring.flat, ring_specs, groups))
            self._inputs.append({k: t.numpy() for k, t in _views(in_flat, in_specs).items()})
        self._plans = plans
        shared = _Shared(str(self.device), mb, self.running, self.cfg.seed, self.cfg.graphs, plans)
        if mode == "process":
            import torch.multiprocessing as tmp

            ctx = tmp.get_context("spawn")
            Q = ctx.Queue
            start = lambda target, args, name: ctx.Process(target=target, args=args, name=name, daemon=True)  # noqa: E731
        else:
            Q = std_queue.Queue
            start = lambda target, args, name: threading.Thread(target=target, args=args, name=name, daemon=True)  # noqa: E731
        self._to_vlm = Q()
        to_action = Q()
        self._vlm_ready_q = Q()
        free_groups = [Q() for _ in plans]
        self._results = Q()
        self._procs = [
            start(vlm_worker, (shared, self._to_vlm, to_action, free_groups, self._vlm_ready_q, self._results),
                  "robion-procdisagg-vlm"),
            start(action_worker, (shared, to_action, free_groups, self._results), "robion-procdisagg-action"),
        ]
        t0 = time.perf_counter()
        for p in self._procs:
            p.start()
        self._rx_stop = threading.Event()
        # The receiver holds the engine weakly, so dropping the engine stops the stage processes.
        self._rx = threading.Thread(target=_receive_loop, args=(weakref.ref(self), self._results, self._rx_stop),
                                    name="procdisagg-results", daemon=True)
        self._rx.start()
        self._finalizer = weakref.finalize(self, _stop_workers, self._procs, self._to_vlm, self._rx_stop)
        with self._ready_cv:
            ok = self._ready_cv.wait_for(lambda: self._ready >= {"vlm", "action"} or self._fatal is not None,
                                         timeout=600)
        if self._fatal is not None or not ok:
            self.close()
            raise RuntimeError(f"procdisagg stages did not start: {self._fatal or 'timeout'}")
        self.prepare_s = time.perf_counter() - t0
        log.info("procdisagg stages ready in %.1f s (%s workers)", self.prepare_s, mode)

    def close(self) -> None:
        """Stop the stage processes (also done when the engine is garbage-collected)."""
        fin = getattr(self, "_finalizer", None)
        if fin is not None:
            fin()

    # ------------------------------------------------------------------ serving

    def _collect_vlm_ready(self, timeout: float | None = None) -> None:
        """Note the VLM process's word that it is ready for a batch; ``timeout``: wait that long for it."""
        try:
            self._vlm_ready_q.get(timeout=timeout) if timeout is not None else self._vlm_ready_q.get_nowait()
        except std_queue.Empty:
            return
        self._vlm_ready = True

    def step(self) -> bool:
        self._collect_vlm_ready()
        if self._fatal is not None:
            raise RuntimeError(self._fatal)
        if not self._vlm_ready:  # one batch at a time in the VLM process, formed when it is ready
            return False
        model, batch, expired = self.queues.take(self.cfg.max_batch)  # sheds expired heads
        self._report_expired(expired)
        if not batch:
            return bool(expired)
        mi = self.names.index(model)
        admitted = time.monotonic()
        v = self._inputs[mi]
        seqs = []
        try:
            with self._inflight_lock:
                for i, r in enumerate(batch):
                    v["images"][i] = r.images
                    v["state"][i] = r.state
                    v["tokens"][i] = r.tokens
                    v[NOISE][i] = r.noise
                    self._seq += 1
                    self._inflight[self._seq] = r
                    seqs.append(self._seq)
        except Exception as exc:
            # An observation that does not fit its slot (a caller past the transport's checks): the batch is
            # answered, and the slot and the VLM's turn stay free, or the model would wait for them for good.
            log.exception("procdisagg: could not stage a batch of %s", model)
            with self._inflight_lock:
                for seq in seqs:
                    self._inflight.pop(seq, None)
            self._emit([Result(r, error=(ErrorCode.INTERNAL, f"inference failed: {type(exc).__name__}"))
                        for r in batch])
            return True
        self._vlm_ready = False
        self._to_vlm.put((mi, seqs, admitted))
        return True

    def run(self, stop: threading.Event) -> None:
        self.queues.reopen()  # closed by the previous run's finish, if any
        while not stop.is_set():
            try:
                if not self.step():
                    if self.queues.depths() and any(self.queues.depths().values()):
                        self._collect_vlm_ready(timeout=0.002)  # waiting for the VLM side
                    else:
                        self.queues.wait(0.005)
            except Exception:
                log.exception("procdisagg front step failed")
                if self._fatal is not None:
                    break
        self.finish()

    def _handle(self, msg: tuple) -> None:
        kind = msg[0]
        if kind == "done":
            out = []
            with self._inflight_lock:
                for seq, t_adm, t_vlm, t_done, actions in msg[1]:
                    r = self._inflight.pop(seq, None)
                    if r is not None:
                        out.append(Result(r, actions=actions, admitted=t_adm, vlm_s=t_vlm - t_adm,
                                          action_s=t_done - t_vlm, done=t_done))
                if not self._inflight:
                    self._drained.notify_all()
            self._emit(out)
        elif kind == "telemetry":
            self.telemetry.add(msg[1])
        elif kind == "error":
            self._fail_seqs(msg[1], msg[2])
        elif kind == "ready":
            with self._ready_cv:
                self._ready.add(msg[1])
                self._ready_cv.notify_all()
        elif kind == "fatal":
            self._fatal = msg[1]
            log.error("procdisagg: %s", msg[1])
            with self._ready_cv:
                self._ready_cv.notify_all()
            with self._inflight_lock:
                seqs = list(self._inflight)
            self._fail_seqs(seqs, msg[1])

    def _fail_seqs(self, seqs: list[int], text: str) -> None:
        out = []
        with self._inflight_lock:
            for s in seqs:
                r = self._inflight.pop(s, None)
                if r is not None:
                    out.append(Result(r, error=(ErrorCode.INTERNAL, text)))
            if not self._inflight:
                self._drained.notify_all()
        self._emit(out)

    def finish(self, timeout_s: float = 30.0) -> None:
        """Answer everything queued (UNAVAILABLE); requests already in the stages complete normally."""
        super().finish()
        with self._inflight_lock:
            self._drained.wait_for(lambda: not self._inflight or self._fatal is not None, timeout=timeout_s)
            seqs = list(self._inflight)
        if seqs:
            self._fail_seqs(seqs, "executor is shutting down")


def _config_fields() -> list[str]:  # for docs/tests: the knobs this engine reads
    return [f.name for f in dataclasses.fields(EngineConfig) if f.name in
            ("max_batch", "policy", "max_queue", "shed_expired", "shed_late", "seed", "graphs", "running_batch",
             "handoff_slots", "procdisagg_workers")]


_ = std_mp  # multiprocessing is used through torch.multiprocessing's spawn context
