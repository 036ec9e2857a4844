"""In-process simulated robots and the capacity search that runs on them.

The engine is measured alone: robots are a driver thread calling ``Engine.submit`` on
each robot's own clock, replies come back through the engine's ``on_results`` sink, and
the network is a model (``shared.netmodel``) added to the measured server latency. No
sockets, no router, so what is measured is the engine, not the I/O layer.

Only the public Engine API is used (constructor sink, ``prepare``, ``submit``,
``run(stop)``, ``models``, ``queues.reopen()``, and ``telemetry`` and ``close`` where an engine
has them), so every engine kind plugs in. An ``EngineHost`` owns one
engine built by a factory: it prepares it once (graph capture can take minutes on a GPU)
and runs it for one epoch at a time; ``run`` returning calls ``finish``, which answers
everything still queued, so nothing leaks from one epoch into the next.

Method (the paper's evaluation, section 6; docs/capacity.md): each robot starts at a random offset in
[0, 1/f) and sends every 1/f s whether or not its replies came; E epochs with fresh
offsets, seeded; SLO attainment = share of sent requests whose end-to-end latency is
within the model's deadline; a request with no reply or an error reply is a miss; the
reported value is the mean over epochs. Capacity = the largest robot count with SLO
attainment >= target, found by exponential growth then bisection.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import threading
import time
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from services.executor.engine import Engine, ResultSink
from services.executor.hosting import free_memory
from services.executor.scheduler import Request, Result
from services.executor.tokens import tokenizer_for
from shared.models.base import VLAModel
from shared.netmodel import NETWORKS, Network
from shared.protocol import ProtocolError

log = logging.getLogger(__name__)

# Deadline per architecture: its Jetson AGX Thor latency in the paper (section 6).
PAPER_DEADLINES_MS: dict[str, float] = {"pi0": 156.0, "xr0": 117.0, "smolvla": 50.0, "groot_n15": 53.0}

INSTRUCTIONS = ("pick up the black bowl and place it on the plate", "open the top drawer of the cabinet",
                "put the cream cheese in the bowl", "turn on the stove and put the moka pot on it")

EngineFactory = Callable[[ResultSink], Engine]

_SPIN_S = 0.0005  # the driver sleeps coarsely until this close to a send, then spins
# A point's attainment is a mean of per-epoch fractions: 0.95, 0.98, 1.0, 0.97 and 1.0 average to exactly 0.98, which
# the float sum makes 0.9799999999999999. Far below any fraction of requests a run can tell apart.
ATTAINMENT_TOLERANCE = 1e-9


def meets(attainment: float, target: float) -> bool:
    """Whether an SLO attainment reaches ``target`` (NaN never does)."""
    return attainment >= target - ATTAINMENT_TOLERANCE


# ----------------------------------------------------------------------------- workload

@dataclass(frozen=True)
class RobotGroup:
    """``robots`` robots using ``model`` (a name the engine serves), each sending at ``hz``."""

    model: str
    robots: int
    hz: float = 2.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.hz) and self.hz > 0) or self.robots < 0:
            raise ValueError(f"RobotGroup {self.model}: hz > 0 and robots >= 0 are needed, got {self.hz} and "
                             f"{self.robots}")


@dataclass
class SimConfig:
    epochs: int = 5
    duration_s: float = 10.0  # sending window of each epoch
    drain_s: float = 1.0  # after the window: how long replies may still come before the rest count as unanswered
    seed: int = 0
    network: str = "wifi7"  # a key of shared.netmodel.NETWORKS
    observations: int = 8  # distinct pre-generated observations per model, shared round-robin by the robots
    lead_s: float = 0.02  # gap between starting the engine thread and the first possible send

    def __post_init__(self) -> None:
        if self.epochs < 1 or self.duration_s <= 0 or self.drain_s < 0:
            raise ValueError("SimConfig: epochs >= 1, duration_s > 0 and drain_s >= 0 are needed")
        if self.network not in NETWORKS:
            raise ValueError(f"unknown network {self.network!r}; known: {', '.join(NETWORKS)}")


@dataclass(frozen=True)
class Send:
    """One scheduled request: ``t`` seconds after the epoch's start, by robot ``robot`` of group ``group``."""

    t: float
    group: int
    robot: int


def epoch_seed(seed: int, epoch: int) -> np.random.SeedSequence:
    return np.random.SeedSequence([seed, epoch])


def make_schedule(workload: Sequence[RobotGroup], duration_s: float, rng: np.random.Generator) -> list[Send]:
    """Every send of one epoch in time order: a random start in [0, 1/f) per robot, then every 1/f s."""
    sends: list[Send] = []
    for g, group in enumerate(workload):
        period = 1.0 / group.hz
        offsets = rng.uniform(0.0, period, size=group.robots)
        for r, off in enumerate(offsets):
            n = int(math.ceil((duration_s - off) / period)) if off < duration_s else 0
            sends.extend(Send(float(off + k * period), g, r) for k in range(n))
    # Ties (same instant) keep a fixed order so a seeded run submits identically.
    sends.sort(key=lambda s: (s.t, s.group, s.robot))
    return sends


@dataclass
class _ModelInputs:
    """Pre-generated observations of one model and the modelled network time of a request."""

    slo_s: float
    images: list[np.ndarray]
    states: list[np.ndarray]
    tokens: list[np.ndarray]
    net_s: list[float]


def _model_inputs(model: VLAModel, slo_s: float, count: int, net: Network, rng: np.random.Generator) -> _ModelInputs:
    io = model.io
    tokenize = tokenizer_for(model)
    down = io.horizon * io.action_dim * 4  # float32 action chunk
    images, states, tokens, net_s = [], [], [], []
    for i in range(count):
        img = rng.integers(0, 256, (len(io.cameras), *io.image_shape), dtype=np.uint8)
        st = rng.standard_normal(io.state_dim).astype(np.float32)
        text = INSTRUCTIONS[i % len(INSTRUCTIONS)]
        images.append(img)
        states.append(st)
        tokens.append(tokenize(text))
        # The robot sends raw images, state and the instruction text; tokenising is the server's job.
        net_s.append(net.latency_s(img.nbytes + st.nbytes + len(text.encode()), down))
    return _ModelInputs(slo_s, images, states, tokens, net_s)


# ----------------------------------------------------------------------------- results

@dataclass
class Stats:
    """Outcome of the requests of one model (or of all, ``overall``) in one epoch, or the mean over epochs."""

    sent: int = 0
    ok: int = 0  # answered with actions
    met: int = 0  # answered with actions within the deadline, end to end
    misses: int = 0  # sent - met: late, error or unanswered
    late: int = 0
    no_reply: int = 0
    errors: dict[str, int] = field(default_factory=dict)  # error replies by code (OVERLOADED: refused at submit)
    slo_attainment: float = float("nan")  # met / sent; over epochs: the mean of the epochs' values
    p50_ms: float = float("nan")  # end-to-end latency of the answered requests; over epochs: mean
    p99_ms: float = float("nan")
    server_p50_ms: float = float("nan")
    epoch_slo_attainment: list[float] = field(default_factory=list)  # only in the mean over epochs
    epoch_p99_ms: list[float] = field(default_factory=list)


@dataclass
class EpochResult:
    epoch: int
    models: dict[str, Stats]
    overall: Stats
    submit_lag_max_ms: float  # how late the driver submitted: a harness problem shows here
    submit_lag_p99_ms: float
    wall_s: float
    telemetry: dict | None = None  # the engine's own per-lockstep summary, when it keeps one


@dataclass
class SimResult:
    workload: list[RobotGroup]
    config: SimConfig
    deadlines_ms: dict[str, float]
    models: dict[str, Stats]
    overall: Stats
    epochs: list[EpochResult]
    submit_lag_max_ms: float
    submit_lag_p99_ms: float  # worst epoch's p99
    stopped_early: bool = False  # an early-stop rule ended the run before all epochs

    def attainment(self, model: str | None = None) -> float:
        return (self.models[model] if model else self.overall).slo_attainment

    def to_dict(self) -> dict:
        return _json_safe(dataclasses.asdict(self))

    def table(self) -> str:
        rows = [f"{'model':<14}{'sent':>7}{'ok':>7}{'miss':>7}{'SLO ms':>8}{'SLO-AT':>9}{'p50 ms':>9}{'p99 ms':>9}"]
        for name, s in [*self.models.items(), ("overall", self.overall)]:
            slo = f"{self.deadlines_ms[name]:.0f}" if name in self.deadlines_ms else "-"
            rows.append(f"{name:<14}{s.sent:>7}{s.ok:>7}{s.misses:>7}{slo:>8}{100 * s.slo_attainment:>8.1f}%"
                        f"{s.p50_ms:>9.1f}{s.p99_ms:>9.1f}")
        rows.append(f"submit lag: max {self.submit_lag_max_ms:.2f} ms, p99 {self.submit_lag_p99_ms:.2f} ms")
        return "\n".join(rows)


def _json_safe(value: Any) -> Any:
    """NaN is not JSON: it becomes null."""
    if isinstance(value, float):
        return None if math.isnan(value) or math.isinf(value) else value
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def _pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else float("nan")


@dataclass
class _Outcome:
    model: str
    slo_s: float
    net_s: float
    sent_at: float = 0.0  # the robot's send time (time.monotonic)
    done: float | None = None  # engine's result.done
    error: str | None = None


def _stats(outcomes: list[_Outcome]) -> Stats:
    s = Stats(sent=len(outcomes))
    e2e, server = [], []
    errors: Counter[str] = Counter()
    for o in outcomes:
        if o.done is None:
            s.no_reply += 1
        elif o.error is not None:
            errors[o.error] += 1
        else:
            s.ok += 1
            srv = o.done - o.sent_at
            lat = srv + o.net_s
            server.append(srv)
            e2e.append(lat)
            if lat <= o.slo_s:
                s.met += 1
            else:
                s.late += 1
    s.errors = dict(errors)
    s.misses = s.sent - s.met
    s.slo_attainment = s.met / s.sent if s.sent else float("nan")
    e2e_ms, server_ms = np.array(e2e) * 1e3, np.array(server) * 1e3
    s.p50_ms, s.p99_ms, s.server_p50_ms = _pct(e2e_ms, 50), _pct(e2e_ms, 99), _pct(server_ms, 50)
    return s


def _mean_stats(per_epoch: list[Stats]) -> Stats:
    def mean(values: list[float]) -> float:
        v = [x for x in values if not math.isnan(x)]
        return float(np.mean(v)) if v else float("nan")

    errors: Counter[str] = Counter()
    for s in per_epoch:
        errors.update(s.errors)
    return Stats(
        sent=sum(s.sent for s in per_epoch), ok=sum(s.ok for s in per_epoch), met=sum(s.met for s in per_epoch),
        misses=sum(s.misses for s in per_epoch), late=sum(s.late for s in per_epoch),
        no_reply=sum(s.no_reply for s in per_epoch), errors=dict(errors),
        slo_attainment=mean([s.slo_attainment for s in per_epoch]), p50_ms=mean([s.p50_ms for s in per_epoch]),
        p99_ms=mean([s.p99_ms for s in per_epoch]), server_p50_ms=mean([s.server_p50_ms for s in per_epoch]),
        epoch_slo_attainment=[s.slo_attainment for s in per_epoch], epoch_p99_ms=[s.p99_ms for s in per_epoch])


class _Collector:
    """The epoch's result sink: matches replies to sends (engine thread) and signals when all are in."""

    def __init__(self, outcomes: dict[str, _Outcome]):
        self._outcomes = outcomes
        self._lock = threading.Lock()
        self._answered = 0
        self._expected = len(outcomes)
        self.all_answered = threading.Event()
        if not outcomes:
            self.all_answered.set()

    def __call__(self, results: list[Result]) -> None:
        # The reply time is when the sink has the result, as a client would, not the engine's own stamp: an
        # engine that hands results over later than it stamps them (a lockstep delivers after launching the
        # next one) must not gain the difference.
        now = time.monotonic()
        with self._lock:
            for r in results:
                o = self._outcomes.get(r.request.id)
                if o is None or o.done is not None:
                    continue  # not this epoch's, or answered twice: the first answer counts
                o.done = max(now, r.done)
                if r.error is not None:
                    o.error = r.error[0].value
                elif r.actions is None:  # no actions and no error met nothing: it counted as met
                    o.error = "INTERNAL"
                self._answered += 1
            if self._answered >= self._expected:
                self.all_answered.set()

    def refused(self, rid: str, code: str) -> None:
        """A submit that raised (queue full): answered at once with that error, as the I/O layer would."""
        with self._lock:
            o = self._outcomes[rid]
            o.done, o.error = time.monotonic(), code
            self._answered += 1
            if self._answered >= self._expected:
                self.all_answered.set()


# ----------------------------------------------------------------------------- engine host

class EngineHost:
    """One engine under test, built by ``factory(sink)``, prepared once, run one epoch at a time.

    ``reuse=True`` keeps the prepared engine across points (graph capture and profiling
    happen once); ``reuse=False`` builds and prepares a fresh one per point (``end_point``
    drops it). The engine is always given this host's forwarding sink, so the harness can
    point replies at each epoch's collector without rebuilding the engine.
    """

    def __init__(self, factory: EngineFactory, reuse: bool = True, label: str = "", join_timeout_s: float = 120.0):
        self.factory = factory
        self.reuse = reuse
        self.label = label
        self.join_timeout_s = join_timeout_s
        self.prepare_s: list[float] = []  # one entry per engine built
        self._engine: Engine | None = None
        self._sink: ResultSink | None = None

    def _forward(self, results: list[Result]) -> None:
        sink = self._sink
        if sink is not None:
            sink(results)

    @property
    def engine(self) -> Engine:
        """The prepared engine, built on first use."""
        if self._engine is None:
            t0 = time.perf_counter()
            engine = self.factory(self._forward)
            engine.prepare()
            self.prepare_s.append(time.perf_counter() - t0)
            log.info("engine %s ready in %.1f s", self.label or type(engine).__name__, self.prepare_s[-1])
            self._engine = engine
        return self._engine

    @contextmanager
    def running(self, sink: ResultSink) -> Iterator[Engine]:
        """Run the engine loop in its own thread while the body drives it; replies go to ``sink``."""
        engine = self.engine
        stop = threading.Event()
        self._sink = sink
        # The previous epoch's finish closed the queues, and run reopens them only once its thread runs:
        # reopen here too, or a robot submitting first would be refused UNAVAILABLE (a miss).
        engine.queues.reopen()
        thread = threading.Thread(target=engine.run, args=(stop,), name=f"engine-{self.label}", daemon=True)
        thread.start()
        try:
            yield engine
        finally:
            stop.set()
            thread.join(self.join_timeout_s)
            self._sink = None
            if thread.is_alive():
                self._engine = None  # never hand a wedged engine to the next epoch
                raise RuntimeError(f"engine {self.label!r} did not stop within {self.join_timeout_s} s")

    def end_point(self) -> None:
        if not self.reuse:
            self.close()

    def close(self) -> None:
        """Drop the engine (and its GPU memory)."""
        if self._engine is None:
            return
        engine, self._engine = self._engine, None
        close = getattr(engine, "close", None)
        if close is not None:  # engines with worker processes (procdisagg) stop them here
            close()
        del engine
        free_memory()


def _as_host(engine: EngineHost | EngineFactory) -> EngineHost:
    return engine if isinstance(engine, EngineHost) else EngineHost(engine)


# ----------------------------------------------------------------------------- simulation

_EPOCH_RUNS = itertools.count()


def _sleep_until(target: float) -> None:
    """Coarse sleep, then spin: time.sleep alone overshoots by up to a scheduler tick."""
    while True:
        left = target - time.monotonic()
        if left <= 0:
            return
        if left > _SPIN_S:
            time.sleep(left - _SPIN_S)


def _telemetry(engine: Engine, phase: str) -> dict | None:
    """The engine's per-lockstep telemetry, when it has any (engines differ; all of it is optional)."""
    tel = getattr(engine, "telemetry", None)
    if tel is None:
        return None
    try:
        if phase == "start":
            clear = getattr(tel, "clear", None)
            if callable(clear):
                clear()
            return None
        out: dict = {}
        summary = getattr(tel, "summary", None)
        if callable(summary):
            out["summary"] = summary()
        records = getattr(tel, "records", None)
        if callable(records):
            combos: Counter[str] = Counter()
            for r in records():
                combos[f"vlm{getattr(r, 'vlm_batch', '?')}+act{getattr(r, 'action_batch', '?')}"
                       f"@sm{getattr(r, 'sm_level', None)}"] += 1
            out["batch_sm_counts"] = dict(combos)
        return _json_safe(out) or None
    except Exception:  # telemetry must never fail a measurement
        log.warning("could not read the engine's telemetry", exc_info=True)
        return None


def _run_epoch(host: EngineHost, workload: Sequence[RobotGroup], cfg: SimConfig, epoch: int,
               inputs: dict[str, _ModelInputs]) -> EpochResult:
    rng = np.random.default_rng(epoch_seed(cfg.seed, epoch))
    schedule = make_schedule(workload, cfg.duration_s, rng)
    # Ids name the run too: an engine reused across points must never have a straggler of an earlier
    # epoch's request (a worker process answering late) count as this epoch's request of the same number.
    run = next(_EPOCH_RUNS)

    # Requests are built before the clock starts; only arrival and deadline are set at send time.
    outcomes: dict[str, _Outcome] = {}
    plan: list[tuple[float, Request, _Outcome]] = []
    for i, s in enumerate(schedule):
        group = workload[s.group]
        mi = inputs[group.model]
        k = s.robot % len(mi.images)
        rid = f"r{run}-e{epoch}-{i}"
        req = Request(id=rid, robot=f"{group.model}/{s.group}/{s.robot}", model=group.model, images=mi.images[k],
                      state=mi.states[k], tokens=mi.tokens[k], arrival=0.0, deadline=0.0)
        outcomes[rid] = out = _Outcome(group.model, mi.slo_s, mi.net_s[k])
        plan.append((s.t, req, out))
    collector = _Collector(outcomes)
    lags = np.zeros(len(plan))
    failed_submits: list[str] = []

    def drive(engine: Engine, t0: float) -> None:
        for j, (t, req, out) in enumerate(plan):
            send = t0 + t
            _sleep_until(send)
            # The robot's clock: the request was sent at ``send``; the engine sees the robot's
            # real deadline, which the network's share of the budget shortens.
            req.arrival = send
            req.deadline = send + out.slo_s - out.net_s
            out.sent_at = send
            lags[j] = time.monotonic() - send
            try:
                engine.submit(req)
            except ProtocolError as exc:
                collector.refused(req.id, exc.code.value)
            except Exception:  # the driver went on without it: the rest of the epoch was never sent
                if not failed_submits:  # one traceback an epoch: one per request slowed the driver itself
                    log.exception("engine.submit failed; such requests count as INTERNAL errors")
                failed_submits.append(req.id)
                collector.refused(req.id, "INTERNAL")

    wall0 = time.monotonic()
    with host.running(collector) as engine:
        _telemetry(engine, "start")
        t0 = time.monotonic() + cfg.lead_s
        driver = threading.Thread(target=drive, args=(engine, t0), name="robot-driver", daemon=True)
        driver.start()
        driver.join()
        # Never before the last send's deadline: a shorter drain would stop the engine on requests that could
        # still be answered in time, and count them as misses.
        end = t0 + cfg.duration_s + max(cfg.drain_s, max((mi.slo_s for mi in inputs.values()), default=0.0))
        collector.all_answered.wait(max(0.0, end - time.monotonic()))
        telemetry = _telemetry(engine, "end")
    if len(failed_submits) > 1:
        log.warning("engine.submit failed for %d requests of epoch %d", len(failed_submits), epoch)
    # Stopping the engine answers what was still queued (with an error): those are misses too.

    by_model: dict[str, list[_Outcome]] = {g.model: [] for g in workload}
    for o in outcomes.values():
        by_model[o.model].append(o)
    lag_ms = lags * 1e3
    return EpochResult(
        epoch=epoch, models={m: _stats(v) for m, v in by_model.items()}, overall=_stats(list(outcomes.values())),
        submit_lag_max_ms=float(lag_ms.max()) if len(lag_ms) else 0.0,
        submit_lag_p99_ms=_pct(lag_ms, 99) if len(lag_ms) else 0.0,
        wall_s=time.monotonic() - wall0, telemetry=telemetry)


class SearchCancelled(Exception):
    """The ``cancel`` event of a simulation or capacity search was set: it ended between epochs."""


def simulate(engine: EngineHost | EngineFactory, workload: Sequence[RobotGroup], cfg: SimConfig | None = None,
             stop_below: float | None = None, cancel: threading.Event | None = None) -> SimResult:
    """Drive simulated robots against one engine for ``cfg.epochs`` epochs and report SLO attainment.

    Deadlines are the engine's ``models[name].slo_s``; observation shapes come from each
    model's ``io``. With ``stop_below``, the run ends as soon as some model's mean SLO
    attainment over all epochs can no longer reach that value (a capacity search only needs
    to know that a point fails, and overloaded points are the slow ones).
    """
    cfg = cfg or SimConfig()
    short = [g for g in workload if g.robots and cfg.duration_s * g.hz < 1]
    if short:  # an epoch would send nothing for them, and its NaN attainment dropped out of the mean
        raise ValueError(f"SimConfig.duration_s {cfg.duration_s:g} s is shorter than one period of {short[0].model} "
                         f"at {short[0].hz:g} Hz")
    host = _as_host(engine)
    served = host.engine.models
    net = NETWORKS[cfg.network]
    unknown = sorted({g.model for g in workload} - set(served))
    if unknown:
        raise ValueError(f"workload uses models the engine does not serve: {unknown}")
    rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, 1 << 20]))
    inputs = {m: _model_inputs(served[m].model, served[m].slo_s, cfg.observations, net, rng)
              for m in sorted({g.model for g in workload})}

    epochs: list[EpochResult] = []
    stopped = False
    for e in range(cfg.epochs):
        if cancel is not None and cancel.is_set():
            raise SearchCancelled()
        epochs.append(_run_epoch(host, workload, cfg, e, inputs))
        if stop_below is not None and e + 1 < cfg.epochs:
            left = cfg.epochs - len(epochs)
            best = min((sum(ep.models[m].slo_attainment for ep in epochs) + left) / cfg.epochs for m in inputs)
            if not meets(best, stop_below):
                stopped = True
                break
    models = {m: _mean_stats([ep.models[m] for ep in epochs]) for m in inputs}
    return SimResult(
        workload=list(workload), config=cfg, deadlines_ms={m: inputs[m].slo_s * 1e3 for m in inputs},
        models=models, overall=_mean_stats([ep.overall for ep in epochs]), epochs=epochs,
        submit_lag_max_ms=max(ep.submit_lag_max_ms for ep in epochs),
        submit_lag_p99_ms=max(ep.submit_lag_p99_ms for ep in epochs), stopped_early=stopped)


# ----------------------------------------------------------------------------- capacity search

LAG_LIMIT = 0.05  # of the deadline: a point whose harness sent later than this (p99, in some epoch) is flagged


@dataclass
class Point:
    """One measured robot count."""

    robots: int
    slo_attainment: float
    p50_ms: float
    p99_ms: float
    passed: bool
    epochs: int  # epochs actually run (fewer when the point was stopped early as failed)
    sent: int
    misses: int
    errors: dict[str, int]
    no_reply: int
    submit_lag_max_ms: float
    wall_s: float
    screened: bool = False  # a screening point of a search (fewer epochs than a full run)
    # How late the harness itself sent (docs/capacity.md, "Send times"): the lag counts against the engine, so a
    # point whose p99 lag is over LAG_LIMIT of the deadline in some epoch measured the host, not only the engine.
    submit_lag_p99_ms: float = 0.0
    epoch_submit_lag_p99_ms: list[float] = field(default_factory=list)
    lag_ok: bool = True
    epoch_slo_attainment: list[float] = field(default_factory=list)
    epoch_p99_ms: list[float] = field(default_factory=list)
    telemetry: list[dict | None] = field(default_factory=list)


class CapacitySearch:
    """Exponential growth from ``start`` until a count fails (or ``max_robots``), then bisection.

    Step-wise (``next`` / ``record``) so a caller can interleave several engines' searches
    point by point. Bisection assumes attainment falls with load and only measures between
    the largest pass and the smallest failure, so the capacity found is a count that passed
    with the next count failing.

    With ``screen_epochs`` the bracket is found with short points (that many epochs each),
    and its two ends are then measured with every epoch (``epochs_next`` says which): the
    candidate, then the count above it. One short epoch sees one draw of the robots' phases
    and can err either way:
    - a candidate that fails its full run ends screening: every later point runs all epochs,
      galloping down (1, 2, 4, ... robots below the latest failure, at least one robot) to a
      full pass, then bisecting;
    - a count above the candidate that passes its full run overrules the screening failures
      at or below it, and the search goes on above it.
    So the reported capacity passed all of its epochs and the count above it failed with all
    of its epochs (or is beyond ``max_robots``).
    """

    def __init__(self, target: float = 0.98, start: int = 1, max_robots: int = 256, growth: float = 2.0,
                 screen_epochs: int | None = None, full_epochs: int | None = None):
        if not 0 < target <= 1 or start < 1 or max_robots < start or growth <= 1:
            raise ValueError("CapacitySearch: 0 < target <= 1, 1 <= start <= max_robots, growth > 1")
        if screen_epochs is not None and (full_epochs is None or not 1 <= screen_epochs < full_epochs):
            raise ValueError("CapacitySearch: screening needs 1 <= screen_epochs < full_epochs")
        self.target = target
        self.max_robots = max_robots
        self.growth = growth
        self.screen_epochs = screen_epochs
        self.full_epochs = full_epochs
        self.points: list[Point] = []
        self.full_points: list[Point] = []  # points run with every epoch (all of them without screening)
        self.lo = 0  # largest count known to pass
        self.hi: int | None = None  # smallest count known to fail
        self._next: int | None = start
        self._confirming = False  # the next point is a screened candidate's full run
        self._full_mode = False  # a candidate failed its full run: no more screening
        self._step = 0  # galloping distance below hi while no full run has passed

    @property
    def done(self) -> bool:
        return self._next is None

    @property
    def capacity(self) -> int:
        return self.lo

    def next(self) -> int | None:
        return self._next

    def epochs_next(self) -> int | None:
        """Epochs for the next point: the screening count while bracketing, None for the caller's full count."""
        if self.screen_epochs is None or self._confirming or self._full_mode:
            return None
        return self.screen_epochs

    def record(self, point: Point) -> None:
        full = self.epochs_next() is None
        self.points.append(point)
        if full:
            self.full_points.append(point)
        n = point.robots
        if point.passed:
            self.lo = max(self.lo, n)
            if full and self.hi is not None and self.hi <= n:
                # A run of every epoch outweighs a screening failure at or below it: the nearest screening
                # failure above it, if any, bounds the search now.
                self.hi = min((p.robots for p in self.points if not p.passed and p.robots > n), default=None)
        else:
            self.hi = n if self.hi is None else min(self.hi, n)
        if full and not point.passed and self.screen_epochs is not None:
            self._full_mode = True
        self._confirming = False
        if self._full_mode:
            self._record_full()
            return
        if self.hi is None and self.lo < self.max_robots:  # still growing
            self._next = min(self.max_robots, max(self.lo + 1, int(self.lo * self.growth)))
            return
        if self.hi is not None and self.hi - self.lo > 1:
            self._next = (self.lo + self.hi) // 2
            if not any(p.robots == self._next for p in self.points):
                return
        # Bracket closed (or the midpoint was already measured): confirm both ends with every epoch, the
        # candidate first. A count that only failed one short epoch does not bound the capacity.
        if self.screen_epochs is not None:
            if self.lo > 0 and not any(p.robots == self.lo and p.passed for p in self.full_points):
                self._next, self._confirming = self.lo, True
                return
            if self.hi is not None and not any(p.robots == self.hi for p in self.full_points):
                self._next, self._confirming = self.hi, True
                return
        self._next = None

    def _record_full(self) -> None:
        assert self.hi is not None
        passes = [p.robots for p in self.full_points if p.passed and p.robots < self.hi]
        if not passes:  # gallop down from the latest failure, never below one robot
            self.lo = 0
            self._step = max(1, 2 * self._step)
            self._next = max(1, self.hi - self._step) if self.hi > 1 else None
            return
        self.lo = max(passes)
        mid = (self.lo + self.hi) // 2
        measured = {p.robots for p in self.full_points}
        self._next = mid if self.hi - self.lo > 1 and mid not in measured else None


class SweepSearch:
    """Every count of a list in order; capacity = largest count such that it and every smaller one passed."""

    def __init__(self, robots: Sequence[int], target: float = 0.98):
        self.target = target
        self.todo = sorted(set(int(r) for r in robots))
        self.points: list[Point] = []

    @property
    def done(self) -> bool:
        return not self.todo

    @property
    def capacity(self) -> int:
        cap = 0
        for p in sorted(self.points, key=lambda p: p.robots):
            if not p.passed:
                break
            cap = p.robots
        return cap

    def next(self) -> int | None:
        return self.todo[0] if self.todo else None

    def epochs_next(self) -> None:
        """A sweep measures every count with all epochs."""
        return None

    def record(self, point: Point) -> None:
        self.points.append(point)
        if point.robots in self.todo:
            self.todo.remove(point.robots)


Search = CapacitySearch | SweepSearch


@dataclass
class CapacityResult:
    model: str
    engine: str
    target: float
    mode: str  # "search" or "sweep"
    capacity: int
    points: list[Point]
    prepare_s: list[float]
    # The search reached max_robots with every count passing: the capacity is a lower bound, not a measurement.
    capped: bool = False

    def to_dict(self) -> dict:
        return _json_safe(dataclasses.asdict(self))


def measure_point(host: EngineHost, model: str, robots: int, hz: float, sim: SimConfig, target: float,
                  early_stop: bool = True, cancel: threading.Event | None = None) -> Point:
    """One point of a curve: ``robots`` robots of ``model`` at ``hz``; the engine is reused or rebuilt per the host."""
    t0 = time.monotonic()
    try:
        res = simulate(host, [RobotGroup(model, robots, hz)], sim, stop_below=target if early_stop else None,
                       cancel=cancel)
    finally:
        host.end_point()
    s = res.models[model]
    return Point(robots=robots, slo_attainment=s.slo_attainment, p50_ms=s.p50_ms, p99_ms=s.p99_ms,
                 passed=meets(s.slo_attainment, target) and not res.stopped_early, epochs=len(res.epochs),
                 sent=s.sent, misses=s.misses, errors=s.errors, no_reply=s.no_reply,
                 submit_lag_max_ms=res.submit_lag_max_ms, wall_s=time.monotonic() - t0,
                 epoch_slo_attainment=s.epoch_slo_attainment, epoch_p99_ms=s.epoch_p99_ms,
                 telemetry=[ep.telemetry for ep in res.epochs], submit_lag_p99_ms=res.submit_lag_p99_ms,
                 epoch_submit_lag_p99_ms=[ep.submit_lag_p99_ms for ep in res.epochs],
                 lag_ok=res.submit_lag_p99_ms <= LAG_LIMIT * res.deadlines_ms[model])


def compare_capacity(hosts: Mapping[str, EngineHost], model: str, hz: float = 2.0, sim: SimConfig | None = None,
                     target: float = 0.98, robots: Sequence[int] | None = None, start: int = 1,
                     max_robots: int = 256, early_stop: bool = True, progress: bool = True,
                     on_point: Callable[[str, Point], None] | None = None,
                     screen_epochs: int | None = None, cancel: threading.Event | None = None) -> dict[str, CapacityResult]:
    """Capacity of ``model`` on each engine, their points interleaved so all see the same machine state.

    ``robots`` given: a sweep over those counts; otherwise a search (exponential growth
    from ``start`` then bisection, at most ``max_robots``). ``on_point(engine, point)``
    is called after each point (e.g. to save partial results). ``screen_epochs`` (search
    only): bracket with points of that many epochs and run all ``sim.epochs`` only on the
    candidate (CapacitySearch). ``cancel`` set: SearchCancelled between epochs.
    """
    sim = sim or SimConfig()
    if screen_epochs is not None and screen_epochs >= sim.epochs:
        screen_epochs = None  # nothing to save: every point runs all epochs anyway
    searches: dict[str, Search] = {
        name: SweepSearch(robots, target) if robots is not None else
        CapacitySearch(target, start, max_robots, screen_epochs=screen_epochs, full_epochs=sim.epochs)
        for name in hosts}
    bar = _progress(model, total=len(hosts) * len(set(robots)) if robots is not None else None, enabled=progress)
    try:
        while not all(s.done for s in searches.values()):
            for name, search in searches.items():  # one point per engine per round
                n = search.next()
                if n is None:
                    continue
                if bar is not None:
                    bar.set_postfix_str(f"{name} @ {n} robots")
                epochs = search.epochs_next()
                point_sim = sim if epochs is None else dataclasses.replace(sim, epochs=epochs)
                point = measure_point(hosts[name], model, n, hz, point_sim, target, early_stop, cancel)
                point.screened = epochs is not None
                search.record(point)
                log.info("%s %s %d robots: SLO-AT %.3f p99 %.1f ms%s", model, name, n, point.slo_attainment,
                         point.p99_ms, "" if point.passed else " (fail)")
                if not point.lag_ok:
                    log.warning("%s %s %d robots: the harness sent late (p99 %.1f ms, over %.0f%% of the deadline): "
                                "this point measured the host as much as the engine", model, name, n,
                                point.submit_lag_p99_ms, 100 * LAG_LIMIT)
                if on_point is not None:
                    on_point(name, point)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix_str(f"{name} {n}: {100 * point.slo_attainment:.1f}%")
    finally:
        if bar is not None:
            bar.close()
    return {name: CapacityResult(model=model, engine=name, target=target,
                                 mode="sweep" if robots is not None else "search", capacity=s.capacity,
                                 points=s.points, prepare_s=list(hosts[name].prepare_s),
                                 capped=s.capacity >= (max(robots) if robots else max_robots))
            for name, s in searches.items()}


def find_capacity(engine: EngineHost | EngineFactory, model: str, hz: float = 2.0, sim: SimConfig | None = None,
                  target: float = 0.98, start: int = 1, max_robots: int = 256, early_stop: bool = True,
                  progress: bool = True, screen_epochs: int | None = None,
                  cancel: threading.Event | None = None) -> CapacityResult:
    """The largest robot count of ``model`` with SLO attainment >= ``target`` on one engine."""
    host = _as_host(engine)
    return compare_capacity({host.label or "engine": host}, model, hz, sim, target, None, start, max_robots,
                            early_stop, progress, screen_epochs=screen_epochs, cancel=cancel)[host.label or "engine"]


def sweep(engine: EngineHost | EngineFactory, model: str, robots: Sequence[int], hz: float = 2.0,
          sim: SimConfig | None = None, target: float = 0.98, progress: bool = True) -> CapacityResult:
    """SLO attainment and p99 at each of ``robots`` (all epochs at every count: curves want full points)."""
    host = _as_host(engine)
    return compare_capacity({host.label or "engine": host}, model, hz, sim, target, robots, early_stop=False,
                            progress=progress)[host.label or "engine"]


def _progress(model: str, total: int | None, enabled: bool):
    if not enabled:
        return None
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    return tqdm(total=total, desc=f"capacity {model}", unit="pt", dynamic_ncols=True)


# ----------------------------------------------------------------------------- engine factories

def served_models(specs: Mapping[str, str], size: str = "tiny", device: str = "cpu", seed: int = 0,
                  deadlines_ms: Mapping[str, float] | None = None) -> dict:
    """``{name: arch}`` -> ``{name: ServedModel}`` built with ``build_model``; deadline: override, else the paper's.

    An architecture the paper has no deadline for (e.g. ``toy``) needs one in ``deadlines_ms``.
    """
    from services.executor.engine import ServedModel
    from shared.models import build_model

    deadlines_ms = dict(deadlines_ms or {})
    out = {}
    for name, arch in specs.items():
        ms = deadlines_ms.get(name, deadlines_ms.get(arch, PAPER_DEADLINES_MS.get(arch)))
        if ms is None:
            raise ValueError(f"no deadline for model {name!r} ({arch}); give one (the paper's cover "
                             f"{', '.join(PAPER_DEADLINES_MS)})")
        out[name] = ServedModel(name, build_model(arch, size, seed=seed, device=device), ms / 1e3)
    return out


def engine_factory(kind: str, models: Mapping, device: str = "cpu", **overrides: Any) -> EngineFactory:
    """A factory for ``make_engine`` with ``EngineConfig(kind=kind, **overrides)``; checks the overrides now."""
    import torch

    from services.executor.engine import make_engine
    from shared.config import EngineConfig

    known = {f.name for f in dataclasses.fields(EngineConfig)}
    bad = sorted(set(overrides) - known)
    if bad:
        raise ValueError(f"EngineConfig has no field(s) {bad}; fields: {', '.join(sorted(known))}")
    cfg = EngineConfig(kind=kind, **overrides)
    dev = torch.device(device)
    models = dict(models)
    return lambda sink: make_engine(models, dataclasses.replace(cfg), dev, sink)
