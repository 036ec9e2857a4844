"""Robion's engine: the VLM and action stages on two streams, advancing in locksteps.

Lockstep k runs the VLM stage of batch k (VLM stream, SM-restricted by the policy) beside
the action stage of batch k-1 (action stream, unrestricted). Requests are admitted only
at a lockstep start; the lockstep ends when both stages have finished. Batch k's handoff
stays in the VLM side's static buffer until lockstep k+1 copies it (one device copy on
the action stream) into the action side's buffer, and batch k-1's actions reach pinned
host memory at the end of its action stage.

One thread drives both streams: graph launches are asynchronous, so launching the action
graph, then the VLM graph, then waiting on two events costs a few microseconds and needs
no barrier between threads. The loop is arranged so that everything not needed to start
the next lockstep (replies, telemetry) happens while the GPU is busy.

The same loop runs on the CPU with ``HostRunner`` (stages run eagerly, in launch order),
which is what the unit tests exercise.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from services.executor.engine import ENGINES, Engine, ResultSink, ServedModel
from services.executor.scheduler import Request, Result
from services.executor.sm import (Level, SMPolicy, StaticLevel, TableLevel, Unrestricted, green_contexts_available,
                                  level_name)
from services.executor.stages import BufferedStages
from services.executor.telemetry import LockstepRecord, Telemetry
from shared.config import EngineConfig
from shared.protocol import ErrorCode

log = logging.getLogger(__name__)


@dataclass
class StageTimes:
    vlm_ms: float
    action_ms: float
    duration_ms: float
    gap_us: float | None  # device idle before this lockstep's first stage (None when unknown)
    gap_last_us: float | None = None  # from the previous lockstep's end to this one's later stage start


class HostRunner:
    """The CPU stand-in for two streams: launches only queue the stages, ``wait`` runs them
    (action first, as launched), so what a stage sees matches the GPU's asynchronous order:
    anything the engine does between launch and wait happens "during" the lockstep.

    Several locksteps may be queued (launch-ahead): ``wait(index)`` runs everything queued up
    to and including lockstep ``index``, in launch order. A VLM stage reads the staging slot
    that was current when it was launched, as its upload on the GPU would.
    """

    asynchronous = False  # stages run inside ``wait``: nothing progresses while the host sleeps

    def __init__(self, ring: int = 8):
        self._ring = [[0.0, 0.0, 0.0, 0.0] for _ in range(ring)]
        self._t = self._ring[0]
        self._index = 0
        self._queued: list[tuple[int, int, object, list[float]]] = []

    def begin(self, index: int, after: int | None = None) -> None:
        self._index = index
        self._t = self._ring[index % len(self._ring)]
        self._t[:] = [0.0, 0.0, 0.0, 0.0]

    def launch_handoff(self, stages: BufferedStages, b: int) -> None:
        self._queued.append((self._index, 2, lambda: stages.handoff(b), self._t))

    def launch_action(self, stages: BufferedStages, b: int, slot: int) -> None:
        self._queued.append((self._index, 3, lambda: stages.action(b, slot), self._t))

    def launch_vlm(self, stages: BufferedStages, b: int, level: Level, after_handoff: bool) -> None:
        slot = stages._cur[b]

        def run() -> None:
            # A later lockstep may already have staged into the other slot (launch-ahead).
            current, stages._cur[b] = stages._cur[b], slot
            try:
                stages.vlm(b, level)
            finally:
                stages._cur[b] = current

        self._queued.append((self._index, 0, run, self._t))

    def end_launch(self) -> None:
        pass

    def done(self, index: int) -> bool:
        return not any(q[0] <= index for q in self._queued)

    def wait(self, index: int | None = None) -> None:
        index = self._index if index is None else index
        run = [q for q in self._queued if q[0] <= index]
        self._queued = [q for q in self._queued if q[0] > index]
        for _, at, fn, t in run:
            t0 = time.perf_counter()
            fn()
            t1 = time.perf_counter()
            if at == 0:
                t[0:2] = [t0, t1]
            elif at == 2:
                t[2:4] = [t0, t1]
            else:  # the action stage's time: its handoff copy and its run, not a VLM stage run between them
                t[3] += t1 - t0

    def measure(self, index: int, after_previous: bool) -> StageTimes:
        vs, ve, as_, ae = self._ring[index % len(self._ring)]
        vlm, act = (ve - vs) * 1e3, (ae - as_) * 1e3
        return StageTimes(vlm, act, vlm + act, None)


@dataclass
class _Events:
    vlm_start: torch.cuda.Event = field(default_factory=lambda: torch.cuda.Event(enable_timing=True))
    vlm_end: torch.cuda.Event = field(default_factory=lambda: torch.cuda.Event(enable_timing=True))
    act_start: torch.cuda.Event = field(default_factory=lambda: torch.cuda.Event(enable_timing=True))
    act_end: torch.cuda.Event = field(default_factory=lambda: torch.cuda.Event(enable_timing=True))
    handoff: torch.cuda.Event = field(default_factory=torch.cuda.Event)
    has_vlm: bool = False
    has_act: bool = False
    last_end: torch.cuda.Event | None = None


class CudaRunner:
    """Launches a lockstep on two CUDA streams and waits for it with events (never a device sync).

    Events live in a ring, so a finished lockstep's timings can still be read one lockstep
    later, while the next one runs. ``begin(index, after=k)`` gates lockstep ``index`` on
    lockstep k's end: each stream's first operation of the lockstep waits (cudaStreamWaitEvent)
    on k's end events, so the lockstep can be issued while k still runs (launch-ahead) and
    still starts only when both of k's stages have finished.
    """

    asynchronous = True

    def __init__(self, device: torch.device, ring: int = 8, green=None, eager_vlm: bool = False):
        self.device = device
        self.vlm_stream = torch.cuda.Stream(device)
        self.action_stream = torch.cuda.Stream(device)
        self.green = green
        self.eager_vlm = eager_vlm  # ungraphed VLM: launch on the level's green stream to restrict it
        self._home = torch.cuda.current_stream(device)
        self._ring = [_Events() for _ in range(ring)]
        self._ev = self._ring[0]
        self._gate: _Events | None = None

    def begin(self, index: int, after: int | None = None) -> None:
        ev = self._ev = self._ring[index % len(self._ring)]
        ev.has_vlm = ev.has_act = False
        ev.last_end = None
        self._gate = self._ring[after % len(self._ring)] if after is not None else None
        self._act_started = False

    def _start_action(self, s: torch.cuda.Stream) -> None:
        """The action side's first operation of the lockstep (its handoff copy, or the action stage launched
        without one): gate it on the lockstep it follows and record act_start, once per lockstep. A second
        record after the copy left the copy out of ungated locksteps' action_ms."""
        if self._act_started:
            return
        gate = self._gate
        # The action stream's own previous work is ordered already; wait for the other stream.
        if gate is not None and gate.has_vlm:
            s.wait_event(gate.vlm_end)
        self._ev.act_start.record(s)
        self._act_started = True

    def launch_handoff(self, stages: BufferedStages, b: int) -> None:
        """First part of the action stage: copy the handoff into the action side's buffers."""
        ev, s = self._ev, self.action_stream
        torch.cuda.set_stream(s)
        self._start_action(s)
        stages.handoff(b)
        ev.handoff.record(s)

    def launch_action(self, stages: BufferedStages, b: int, slot: int) -> None:
        ev, s = self._ev, self.action_stream
        torch.cuda.set_stream(s)
        self._start_action(s)
        stages.action(b, slot)
        ev.act_end.record(s)
        ev.has_act = True

    def launch_vlm(self, stages: BufferedStages, b: int, level: Level, after_handoff: bool) -> None:
        ev = self._ev
        s = self.green.stream(level) if self.eager_vlm and level is not None else self.vlm_stream
        torch.cuda.set_stream(s)
        gate = self._gate
        if gate is not None:
            if gate.has_act:
                s.wait_event(gate.act_end)
            # Eager VLMs run on the level's green stream or, unrestricted, on vlm_stream: the previous one may
            # have run on another stream than this one, so wait for its end (on the same stream it is a no-op).
            if gate.has_vlm and self.eager_vlm:
                s.wait_event(gate.vlm_end)
        ev.vlm_start.record(s)
        if after_handoff:
            # Same model and batch size as the action stage's batch: this VLM overwrites the
            # buffer the handoff copy is reading.
            s.wait_event(ev.handoff)
        stages.vlm(b, level)
        ev.vlm_end.record(s)
        ev.has_vlm = True

    def end_launch(self) -> None:
        torch.cuda.set_stream(self._home)

    def done(self, index: int) -> bool:
        """Whether lockstep ``index`` has finished (event queries, no waiting)."""
        ev = self._ring[index % len(self._ring)]
        return (not ev.has_vlm or ev.vlm_end.query()) and (not ev.has_act or ev.act_end.query())

    def wait(self, index: int | None = None) -> None:
        ev = self._ev if index is None else self._ring[index % len(self._ring)]
        if ev.has_vlm:
            ev.vlm_end.synchronize()
        if ev.has_act:
            ev.act_end.synchronize()

    def measure(self, index: int, after_previous: bool) -> StageTimes:
        """Timings of a finished lockstep; ``after_previous``: it followed lockstep index-1 without idling."""
        ev = self._ring[index % len(self._ring)]
        ref = ev.vlm_start if ev.has_vlm else ev.act_start
        starts, ends = [(0.0, ref)], []
        vlm_ms = act_ms = 0.0
        if ev.has_vlm:
            vlm_ms = ev.vlm_start.elapsed_time(ev.vlm_end)
            ends.append((vlm_ms, ev.vlm_end))
        if ev.has_act:
            a0 = ref.elapsed_time(ev.act_start) if ev.has_vlm else 0.0
            act_ms = ev.act_start.elapsed_time(ev.act_end)
            starts.append((a0, ev.act_start))
            ends.append((a0 + act_ms, ev.act_end))
        first = min(t for t, _ in starts)
        last, ev.last_end = max(ends, key=lambda te: te[0])
        gap_us = gap_last_us = None
        prev = self._ring[(index - 1) % len(self._ring)]
        if after_previous and prev.last_end is not None:
            to_ref = prev.last_end.elapsed_time(ref)
            gap_us = (to_ref + first) * 1e3
            gap_last_us = (to_ref + max(t for t, _ in starts)) * 1e3
        return StageTimes(vlm_ms, act_ms, last - first, gap_us, gap_last_us)


@dataclass
class _Batch:
    model: str
    stages: BufferedStages
    requests: list[Request]
    admitted: float
    lockstep: int
    vlm_end: float = 0.0
    failed: bool = False  # answered INTERNAL already: a later failure of its lockstep must not answer it again

    @property
    def b(self) -> int:
        return len(self.requests)


@dataclass
class _Launched:
    index: int
    start: float
    vlm: _Batch | None
    act: _Batch | None
    slot: int
    level: Level
    cpu_gap_us: float | None
    after_previous: bool
    end: float = 0.0
    decided: float = 0.0  # perf_counter() when the scheduler was asked for its batch
    issued: float = 0.0  # perf_counter() when everything of the lockstep was enqueued
    gpu_start: float = 0.0  # perf_counter() estimate of when the GPU could start it
    ahead: bool = False  # issued while the previous lockstep still ran (its host cost hidden)
    lead_us: float | None = None  # how long before the previous lockstep's observed end it was issued
    admit_early_us: float | None = None  # how long before that end its batch was admitted
    slack_us: float | None = None  # the launch-ahead slack in force when it was decided
    vlm_open: bool = False  # action part issued ahead, VLM part (the admission decision) still to come
    launch_us: float = 0.0  # host time of all its launch parts
    wake_late_us: float | None = None  # how late the engine thread woke for it (sleep overshoot)


def _combo_key(launch: _Launched) -> tuple:
    vlm, act = launch.vlm, launch.act
    return (vlm.stages.arch if vlm else None, vlm.b if vlm else 0, act.stages.arch if act else None,
            act.b if act else 0, launch.level)


def batch_sizes(max_batch: int) -> list[int]:
    return [1 << i for i in range(max_batch.bit_length()) if 1 << i <= max_batch]


class LockstepEngine(Engine):
    """The two-stream lockstep engine; the SM policy is what the comparison engines vary."""

    LAUNCH_AHEAD_SLACK_US = 100.0  # least slack: wake this much before "predicted end - launch time"
    AHEAD_SLACK_UP_US = 50.0  # added to the slack after a late launch-ahead
    AHEAD_SLACK_DOWN_US = 5.0  # taken off after one in time
    AHEAD_SLACK_MAX_US = 5000.0
    AHEAD_NAP_S = 0.0005  # longest sleep between checks of the running lockstep's end events

    def __init__(self, models: dict[str, ServedModel], cfg: EngineConfig, device: torch.device,
                 on_results: ResultSink, sm_policy: SMPolicy | None = None, launch_ahead: bool | None = None,
                 launch_ahead_slack_us: float | None = None):
        """``launch_ahead``: issue lockstep k+1 shortly before lockstep k is predicted to end,
        gated on k's end events (default: on with CUDA, off with the CPU runner, where stages
        run only when waited on); ``launch_ahead_slack_us``: how much earlier than "predicted
        end minus the measured launch time" to wake (default ``LAUNCH_AHEAD_SLACK_US``). Both
        can also come from ``cfg`` (attributes of the same names), when it has them."""
        super().__init__(models, cfg, device, on_results)
        if launch_ahead is None:
            launch_ahead = getattr(cfg, "launch_ahead", None)
        if launch_ahead_slack_us is None:
            launch_ahead_slack_us = getattr(cfg, "launch_ahead_slack_us", None)
        self._launch_ahead_opt = launch_ahead
        self._launch_ahead = bool(launch_ahead)  # resolved in prepare()
        self.launch_ahead_slack_us = self.LAUNCH_AHEAD_SLACK_US if launch_ahead_slack_us is None \
            else float(launch_ahead_slack_us)
        self._ahead: _Launched | None = None  # issued ahead, gated on the running lockstep's end
        self._issued_part: _Launched | None = None  # the launch-ahead on the GPU while it is being completed
        self._durations: dict[tuple, float] = {}  # EMA of lockstep durations (ms) by (vlm, b, action, b, level)
        self._table_ms: dict[tuple, dict[str, float]] = {}  # profiled lockstep times, before an EMA exists
        self._launch_ema_us = 0.0  # EMA of the host time to decide and issue a lockstep
        self._slack_us = self.launch_ahead_slack_us  # adapted between the floor and AHEAD_SLACK_MAX_US
        self.ahead_missed = 0  # locksteps that ended before the engine woke to launch the next one
        self.batch_sizes = batch_sizes(cfg.max_batch)
        self.sm_policy = sm_policy
        self.table_path: Path | None = None  # the SM table file prepare() used or profiled into (table policy)
        self.telemetry = Telemetry(path=cfg.telemetry_file)
        self.stages: dict[str, BufferedStages] = {}
        self.runner: HostRunner | CudaRunner | None = None
        self.green = None
        self.table = None  # the profiled SM table in use, when the policy is table-driven
        self.prepare_s: dict[str, float] = {}
        self._pending: _Batch | None = None  # passed the VLM stage; its action stage is next
        self._last: _Launched | None = None  # finished; replies and telemetry not yet out
        self._index = 0
        self._last_end = 0.0
        self._back_to_back = False
        self._expected: dict[tuple[str, str, int], float] = {}  # EMA of stage times (ms) by (arch, stage, batch)
        self._account_failed = False  # a lockstep's timings could not be recorded (logged once)
        # Noise is drawn when a request is submitted (seeded, per model, in arrival order), so
        # drawing it costs the lockstep loop nothing and prestaging copies it with the observations.

    # ------------------------------------------------------------------ start-up

    def _graphed(self) -> bool:
        return self.device.type == "cuda" and self.cfg.graphs

    def prepare(self) -> None:
        t0 = time.perf_counter()
        if self.device.type != "cuda":
            self.runner = HostRunner()
            self.stages = {name: BufferedStages(m.model, self.device, self.batch_sizes, self.cfg.seed)
                           for name, m in self.models.items()}
            for st in self.stages.values():
                st.allocate()
            if self.sm_policy is None:
                self.sm_policy = Unrestricted()
            self._launch_ahead = bool(self._launch_ahead_opt)
            self.prepare_s["total"] = time.perf_counter() - t0
            return
        self._prepare_cuda()
        self._launch_ahead = self.runner.asynchronous if self._launch_ahead_opt is None else bool(self._launch_ahead_opt)
        if self.table is not None:
            self._table_ms = {e.combo: dict(e.times_ms) for e in self.table.entries}
        self.prepare_s["total"] = time.perf_counter() - t0
        log.info("lockstep engine ready in %.1f s (%s)", self.prepare_s["total"],
                 ", ".join(f"{k} {v:.1f} s" for k, v in self.prepare_s.items() if k != "total"))

    def _prepare_cuda(self) -> None:
        from services.executor import profiler
        from services.executor.graphs import GraphPools, GraphStages
        from services.executor.sm import GreenStreams, sm_count, sm_levels

        torch.cuda.set_device(self.device)
        t0 = time.perf_counter()
        self.runner = CudaRunner(self.device)
        pools = GraphPools.create() if self._graphed() else None
        if self._graphed():
            self.stages = {name: GraphStages(m.model, self.device, self.batch_sizes, self.cfg.seed, pools, None,
                                             self.runner.vlm_stream, self.runner.action_stream, self._stream_sms())
                           for name, m in self.models.items()}
        else:
            self.stages = {name: BufferedStages(m.model, self.device, self.batch_sizes, self.cfg.seed)
                           for name, m in self.models.items()}
        for st in self.stages.values():
            st.allocate()
        torch.cuda.synchronize(self.device)
        self.prepare_s["buffers"] = time.perf_counter() - t0

        policy = self.sm_policy or self._policy_from_config()
        by_arch = {}
        for st in self.stages.values():
            by_arch.setdefault(st.arch, st)
        missing: list[tuple[str, int, str, int]] = []
        levels_needed: set[Level] = set()
        if isinstance(policy, _PendingTable):
            table = policy.table
            self.table_path = policy.path
            served = table.for_archs(sorted(by_arch))
            missing = profiler.missing_combos(table, sorted(by_arch), self.batch_sizes)
            if missing and not self._graphed():
                raise RuntimeError("profiling SM levels needs CUDA graphs (engine.graphs: true)")
            levels_needed |= set(served.best_levels().values()) | set(served.action_confine.values())
            if missing:
                levels_needed |= set(sm_levels(sm_count(self.device)))
        else:
            for st in self.stages.values():
                for b in self.batch_sizes:
                    levels_needed |= policy.levels_for(st.arch, b)
        if any(lv is not None for lv in levels_needed):
            if not green_contexts_available():
                raise RuntimeError("SM restriction needs torch.cuda.green_contexts (torch >= 2.10 built with CUDA 12.4+)")
            t1 = time.perf_counter()
            self.green = GreenStreams(self.device, sorted(lv for lv in levels_needed if lv is not None))
            self.runner.green = self.green
            self.runner.eager_vlm = not self._graphed()
            for st in self.stages.values():
                if isinstance(st, GraphStages):
                    st.green = self.green
            self.prepare_s["green_contexts"] = time.perf_counter() - t1

        if self._graphed():
            t1 = time.perf_counter()
            for st in self.stages.values():
                if isinstance(policy, _PendingTable):  # as the table serves them, or as it timed them to profile more
                    st.set_action_plans(self._action_plans(table.timing_plans() if missing else served.plans(),
                                                           st.arch))
                else:
                    st.capture_action()
            self.prepare_s["capture"] = time.perf_counter() - t1

        if isinstance(policy, _PendingTable):
            if missing:
                t1 = time.perf_counter()
                table = profiler.profile(by_arch, self.runner, self.batch_sizes, sm_levels(sm_count(self.device)),
                                         combos=missing, table=table, repeats=self.cfg.profile_repeats,
                                         total_sms=sm_count(self.device))
                table.save(policy.path)
                self.prepare_s["profile"] = time.perf_counter() - t1
                log.info("SM table profiled in %.1f s, saved to %s", table.profile_s, policy.path)
                # Profiling may have found new candidate action graphs (on one model per architecture).
                served = table.for_archs(sorted(by_arch))
                t1 = time.perf_counter()
                for st in self.stages.values():
                    st.set_action_plans(self._action_plans(served.plans(), st.arch))
                self.prepare_s["capture"] = self.prepare_s.get("capture", 0.0) + time.perf_counter() - t1
            used = {k: v for k, v in served.plans().items() if v != (None, None)}
            if used:
                log.info("action graphs planned (SMs) or confined (beside a VLM level) for these models: %s",
                         ", ".join(f"{k} {'confined ' + str(c) if c else 'planned ' + str(p)}"
                                   for k, (p, c) in sorted(used.items())))
            self.table = served
            policy = TableLevel(served.best_levels())
        self.sm_policy = policy

        if self._graphed():
            t1 = time.perf_counter()
            for st in self.stages.values():
                keep = {b: policy.levels_for(st.arch, b) for b in self.batch_sizes}
                st.drop_vlm(keep)
                for b in self.batch_sizes:
                    st.capture_vlm(b, keep[b])
            torch.cuda.synchronize(self.device)
            self.prepare_s["capture"] = self.prepare_s.get("capture", 0.0) + time.perf_counter() - t1

    def _action_plans(self, plans: dict, arch: str) -> dict[int, tuple[int | None, int | None]]:
        """Batch -> (SMs the action graph is planned for, VLM level it is confined beside), from
        the table's "arch|batch" -> (SMs, level) map; (None, None): as torch plans it."""
        from services.executor.profiler import action_key

        return {b: plans.get(action_key(arch, b), (None, None)) for b in self.batch_sizes}

    def _stream_sms(self) -> tuple[int | None, int | None]:
        """SMs of the runner's VLM and action streams when they are partitions of their own
        (None: the whole GPU; green levels are handled per graph)."""
        return None, None

    def _policy_from_config(self) -> SMPolicy:
        from services.executor import profiler

        kind = self.cfg.sm_policy
        if kind == "none":
            return Unrestricted()
        if kind == "static":
            return StaticLevel(self.cfg.static_sms)
        if not green_contexts_available():
            log.warning("green contexts unavailable: serving without SM restriction")
            return Unrestricted()
        archs = sorted({st.arch for st in self.stages.values()})
        path, table = profiler.locate_table(self.device, archs, self.cfg.max_batch, self.cfg.sm_table,
                                            self.cfg.profile_dir)
        return _PendingTable(path, table)

    # ------------------------------------------------------------------ serving loop

    def step(self) -> bool:
        return self._step(admit=True)

    def _step(self, admit: bool) -> bool:
        """One lockstep: issue it (unless it was issued ahead), do the host work of the
        previous one while it runs, issue the next one ahead of its end, wait for its end."""
        runner = self.runner
        cur, self._ahead = self._ahead, None
        expired: list[Request] = []
        if cur is None:
            cur, expired = self._launch(admit, None)
            if cur is None:
                # Nothing ran: let the last lockstep's replies out and let the caller idle.
                self._book()
                self._report_expired(expired)
                self._back_to_back = False
                return bool(expired)
        elif cur.vlm_open:  # its action part went ahead; its VLM part was not decided before the end
            expired = self._decide_vlm(cur, admit, None)
        if admit:
            self._prestage()
        self._book()  # the previous lockstep's replies and telemetry, while this one runs
        self._report_expired(expired)
        nxt = None
        if admit and self._launch_ahead:
            self._issued_part = None
            try:
                nxt, expired = self._launch_next(cur)
                self._report_expired(expired)
            except Exception:  # the running lockstep still completes
                log.exception("launching lockstep %d ahead failed", self._index)
                # A lockstep already (partly) on the GPU keeps its batches: if its VLM part is
                # still open it is decided after this lockstep's end, as when a launch-ahead
                # comes too late.
                nxt = self._issued_part
            self._issued_part = None
        try:
            runner.wait(cur.index)
        except Exception as exc:
            self._pending = self._ahead = None
            self._fail([b for b in (cur.act, cur.vlm, nxt.vlm if nxt else None) if b is not None], exc)
            raise
        end = time.perf_counter()
        self._last_end = end
        self._back_to_back = True
        cur.end = time.monotonic()
        if cur.vlm is not None:
            cur.vlm.vlm_end = cur.end
        if nxt is not None:
            nxt.gpu_start = end  # it was waiting on this end
            if nxt.ahead and not nxt.vlm_open:
                nxt.lead_us = (end - nxt.issued) * 1e6
                nxt.admit_early_us = (end - nxt.decided) * 1e6
        self._ahead = nxt
        self._last = cur
        return True

    def _launch(self, admit: bool, after: _Launched | None) -> tuple[_Launched | None, list[Request]]:
        """Decide lockstep ``self._index`` (scheduler pick, SM level) and issue it on the streams.

        ``after``: the lockstep still running, which this one is gated on (launch-ahead);
        None when the previous lockstep's end has been observed already.
        """
        runner = self.runner
        act = self._pending
        index = self._index
        expired: list[Request] = []
        vlm = None
        decided = time.perf_counter()
        try:
            runner.begin(index, after.index if after is not None else None)
            if admit:
                model, reqs, expired = self.queues.take(self.cfg.max_batch)
                if reqs:
                    vlm = _Batch(model, self.stages[model], reqs, time.monotonic(), index)
            if act is None and vlm is None:
                return None, expired
            if act is not None:
                runner.launch_handoff(act.stages, act.b)
            # Launching costs host time (a graph of ~1000 kernels takes ~100 us to submit):
            # issue the stage expected to take longer first, so the lockstep's critical path starts first.
            vlm_first = vlm is not None and act is not None and \
                self._expected.get((vlm.stages.arch, "vlm", vlm.b), 0.0) > \
                self._expected.get((act.stages.arch, "action", act.b), 0.0)
            if act is not None and not vlm_first:
                runner.launch_action(act.stages, act.b, index & 1)
            level = None
            if vlm is not None:
                try:
                    level = self.sm_policy.level(vlm.stages.arch, vlm.b, act.stages.arch if act else None,
                                                 act.b if act else 0)
                    vlm.stages.stage(vlm.b, vlm.requests)
                    runner.launch_vlm(vlm.stages, vlm.b, level,
                                      after_handoff=act is not None and act.stages is vlm.stages and act.b == vlm.b)
                except Exception as exc:
                    if act is None:
                        raise
                    # Only the VLM batch fails (as in _decide_vlm): the action batch's handoff is issued already,
                    # and its own stage still runs this lockstep.
                    self._fail([vlm], exc)
                    vlm, level = None, None
            if act is not None and vlm_first:
                runner.launch_action(act.stages, act.b, index & 1)
            runner.end_launch()
        except Exception as exc:
            runner.end_launch()
            self._pending = None
            self._fail([b for b in (act, vlm) if b is not None], exc)
            # The take already removed these from the queues, and the caller never sees them once we raise.
            self._report_expired(expired)
            raise
        issued = time.perf_counter()
        self._note_launch((issued - decided) * 1e6)
        launch = _Launched(index, time.monotonic(), vlm, act, index & 1, level, None, self._back_to_back,
                           decided=decided, issued=issued, gpu_start=decided, launch_us=(issued - decided) * 1e6)
        if after is None:
            if self._back_to_back:  # host time on the critical path: the GPU idled for all of it
                launch.cpu_gap_us = (issued - self._last_end) * 1e6
        else:
            launch.after_previous = True
            # Issued before the running lockstep ended (checked after issuing, so a lockstep that
            # ended while this one was being issued counts as late, with its whole launch time
            # as the host gap: an upper bound).
            launch.ahead = self._still_running(after.index)
            launch.cpu_gap_us = 0.0 if launch.ahead else (issued - decided) * 1e6
        self._index += 1
        self._pending = vlm
        return launch, expired

    def _launch_next(self, cur: _Launched) -> tuple[_Launched | None, list[Request]]:
        """Launch-ahead of the lockstep after ``cur``, gated on ``cur``'s end events, in two parts.

        1. At once (``cur`` has just started): the action part, which needs no decision (it is
           the batch whose VLM stage ``cur`` runs): handoff copy, action graph, output copy.
        2. Shortly before ``cur`` is predicted to end: the admission decision (scheduler pick,
           SM level) and the VLM part. Only this part's host time sits between the decision
           and ``cur``'s end, so only it delays admission.

        The wake-up comes ``VLM-part launch EMA + slack`` before the predicted end. The slack
        adapts: a VLM part that ``cur``'s end overtook raises it by ``AHEAD_SLACK_UP_US``, one
        in time lowers it by ``AHEAD_SLACK_DOWN_US`` down to ``launch_ahead_slack_us``, so
        about one in (up/down + 1) is late at equilibrium. Without a prediction, or when
        ``cur`` ends first, the VLM part is decided after the end (part 1 still ran ahead)."""
        runner = self.runner
        nxt = self._issue_action_ahead(cur) if self._pending is not None else None
        self._issued_part = nxt  # issued on the GPU: must survive a failure below (see step)
        woke = wake = None
        if runner.asynchronous:
            end = self._predict_end(cur)
            if end is None:
                return nxt, []
            wake = end - (self._launch_ema_us + self._slack_us) * 1e-6
            # Sleep (releasing the GIL) in short naps, checking the events between them, so a
            # lockstep shorter than predicted leaves the GPU idle for at most about one nap.
            while True:
                if runner.done(cur.index):
                    self.ahead_missed += 1
                    self._slack_us = min(self._slack_us + self.AHEAD_SLACK_UP_US, self.AHEAD_SLACK_MAX_US)
                    return nxt, []
                now = time.perf_counter()
                delay = wake - now
                if delay <= 20e-6:
                    woke = now
                    break
                time.sleep(min(delay, self.AHEAD_NAP_S))
        if nxt is None:
            nxt, expired = self._launch(True, cur)
            if nxt is None:
                return None, expired
        else:
            expired = self._decide_vlm(nxt, True, cur)
        nxt.slack_us = self._slack_us
        if woke is not None:
            nxt.wake_late_us = (woke - wake) * 1e6
        if nxt.ahead:
            self._slack_us = max(self._slack_us - self.AHEAD_SLACK_DOWN_US, self.launch_ahead_slack_us)
        else:
            self._slack_us = min(self._slack_us + self.AHEAD_SLACK_UP_US, self.AHEAD_SLACK_MAX_US)
        return nxt, expired

    def _note_launch(self, us: float) -> None:
        """EMA of the host time from an admission decision to its lockstep's (VLM part's) issue,
        fed by every launch (whole launches, made when nothing went ahead, are the longer kind:
        a conservative start)."""
        self._launch_ema_us = us if self._launch_ema_us == 0.0 else 0.9 * self._launch_ema_us + 0.1 * us

    def _issue_action_ahead(self, cur: _Launched) -> _Launched | None:
        """Part 1 of launch-ahead: lockstep ``self._index``'s action part, behind ``cur``'s end."""
        runner = self.runner
        act, index = self._pending, self._index
        t0 = time.perf_counter()
        try:
            runner.begin(index, cur.index)
            runner.launch_handoff(act.stages, act.b)
            runner.launch_action(act.stages, act.b, index & 1)
        except Exception as exc:
            runner.end_launch()
            self._pending = None
            log.exception("issuing lockstep %d's action stage ahead failed", index)
            self._fail([act], exc)
            return None
        runner.end_launch()
        t1 = time.perf_counter()
        self._index += 1
        self._pending = None
        return _Launched(index, time.monotonic(), None, act, index & 1, None, None, True, decided=t1, issued=t1,
                         gpu_start=t1, vlm_open=True, launch_us=(t1 - t0) * 1e6)

    def _decide_vlm(self, launch: _Launched, admit: bool, after: _Launched | None) -> list[Request]:
        """Part 2: admit the VLM batch of ``launch`` (whose action part is issued) and issue it.
        ``after``: the lockstep still running (launch-ahead), or None once its end was observed."""
        runner = self.runner
        act = launch.act
        decided = time.perf_counter()
        vlm, level, expired = None, None, []
        try:
            if admit:
                model, reqs, expired = self.queues.take(self.cfg.max_batch)
                if reqs:
                    vlm = _Batch(model, self.stages[model], reqs, time.monotonic(), launch.index)
            if vlm is not None:
                level = self.sm_policy.level(vlm.stages.arch, vlm.b, act.stages.arch, act.b)
                vlm.stages.stage(vlm.b, vlm.requests)
                runner.launch_vlm(vlm.stages, vlm.b, level, after_handoff=act.stages is vlm.stages and act.b == vlm.b)
        except Exception as exc:  # the action part runs on; only this batch fails
            log.exception("issuing lockstep %d's VLM stage failed", launch.index)
            if vlm is not None:
                self._fail([vlm], exc)
            vlm, level = None, None
        finally:
            runner.end_launch()
        issued = time.perf_counter()
        launch.vlm, launch.level, launch.vlm_open = vlm, level, False
        launch.decided, launch.issued = decided, issued
        launch.launch_us += (issued - decided) * 1e6
        self._note_launch((issued - decided) * 1e6)
        self._pending = vlm
        if after is None:
            launch.ahead = False
            if self._back_to_back:  # the VLM part waited for the host after the end was seen
                launch.cpu_gap_us = (issued - self._last_end) * 1e6
        else:
            launch.ahead = self._still_running(after.index)
            launch.cpu_gap_us = 0.0 if launch.ahead else (issued - decided) * 1e6
        return expired

    def _still_running(self, index: int) -> bool:
        """Whether lockstep ``index`` is still running. Asked right after a batch left the queues and was issued,
        so it must not raise: a device fault raised here lost that batch and the requests its take shed. The
        wait for lockstep ``index`` meets the same fault and fails what was issued, as designed."""
        try:
            return not self.runner.done(index)
        except Exception:
            log.exception("querying the end of lockstep %d failed", index)
            return False

    def _predict_end(self, cur: _Launched) -> float | None:
        """perf_counter() time at which ``cur`` should end: its start on the GPU (the previous
        lockstep's observed end, or its own issue time) plus the EMA of such locksteps' durations,
        or the SM table's profiled time for the combination before one has run."""
        key = _combo_key(cur)
        ms = self._durations.get(key)
        if ms is None and self.table is not None and cur.vlm is not None and cur.act is not None:
            entry = self._table_ms.get(key[:4])
            if entry is not None:
                ms = entry.get(level_name(cur.level))
        if ms is None:
            return None
        return cur.gpu_start + ms * 1e-3

    def _prestage(self) -> None:
        # Only an optimisation (``stage`` copies again when it missed): a failure here must not
        # lose the lockstep just issued, which ``_step`` holds only in a local until its end.
        try:
            model, reqs = self.queues.peek(self.cfg.max_batch)
            if reqs:
                self.stages[model].prestage(len(reqs), reqs)
        except Exception:
            log.exception("prestaging the next batch failed")

    def _book(self) -> None:
        """Replies of the last finished lockstep, then its timings and telemetry. Never raises:
        it runs while the next lockstep is in flight, which an exception here would lose."""
        done, self._last = self._last, None
        if done is None:
            return
        act = done.act
        if act is not None:
            try:
                out = act.stages.result(act.b, done.slot).copy()
            except Exception as exc:
                self._fail([act], exc)
            else:
                self._emit([Result(r, actions=out[i], admitted=act.admitted, vlm_s=act.vlm_end - act.admitted,
                                   action_s=done.end - act.vlm_end, done=done.end, lockstep=act.lockstep)
                            for i, r in enumerate(act.requests)])
        try:
            self._account(done)
        except Exception:  # statistics only; log the first failure, not one per lockstep
            if not self._account_failed:
                log.exception("recording lockstep %d's timings failed", done.index)
            self._account_failed = True

    def _account(self, done: _Launched) -> None:
        """A finished lockstep's timings into the EMAs (launch-ahead, stage order) and telemetry."""
        act = done.act
        t = self.runner.measure(done.index, done.after_previous)
        vlm = done.vlm
        for batch, stage, ms in ((vlm, "vlm", t.vlm_ms), (act, "action", t.action_ms)):
            if batch is not None:
                key = (batch.stages.arch, stage, batch.b)
                self._expected[key] = ms if key not in self._expected else 0.8 * self._expected[key] + 0.2 * ms
        key = _combo_key(done)
        prev = self._durations.get(key)
        self._durations[key] = t.duration_ms if prev is None else 0.8 * prev + 0.2 * t.duration_ms
        self.telemetry.add(LockstepRecord(
            index=done.index, start=done.start,
            vlm_model=vlm.model if vlm else None, vlm_arch=vlm.stages.arch if vlm else None, vlm_batch=vlm.b if vlm else 0,
            action_model=act.model if act else None, action_arch=act.stages.arch if act else None,
            action_batch=act.b if act else 0, sm_level=done.level, duration_ms=t.duration_ms, vlm_ms=t.vlm_ms,
            action_ms=t.action_ms, cpu_gap_us=done.cpu_gap_us, gpu_gap_us=t.gap_us, gpu_gap_last_us=t.gap_last_us,
            launch_us=done.launch_us, ahead=done.ahead, lead_us=done.lead_us,
            admit_early_us=done.admit_early_us, slack_us=done.slack_us, wake_late_us=done.wake_late_us))

    def _fail(self, batches: list[_Batch], exc: Exception) -> None:
        log.error("lockstep %d failed: %r", self._index, exc)
        # A batch can fail twice (a failed action part issued ahead, then its VLM lockstep's wait on a
        # device whose fault is sticky); its requests get one answer.
        batches = [b for b in batches if not b.failed]
        for b in batches:
            b.failed = True
        self._emit([Result(r, error=(ErrorCode.INTERNAL, f"inference failed: {type(exc).__name__}"))
                    for b in batches for r in b.requests])

    def finish(self) -> None:
        """Complete the batch already past its VLM stage, then answer everything still queued."""
        try:
            while self._pending is not None or self._ahead is not None:
                self._step(admit=False)
        except Exception:
            log.exception("could not complete the last batch at shutdown")
        try:
            self._book()
            super().finish()
        finally:
            # A later run() (the capacity harness reuses the engine between epochs) starts from idle: its first
            # lockstep's gap must not span the pause.
            self._back_to_back = False
            self.telemetry.close()


@dataclass
class _PendingTable:
    """A table-driven policy before start-up resolved it (the table may still need profiling)."""

    path: Path
    table: "object"


class RobionEngine(LockstepEngine):
    """``engine.kind: robion``: lockstep engine with the profiled (table-driven) SM restriction."""


ENGINES["robion"] = RobionEngine
