"""Per-model FIFO queues and the policy that picks which queue a batch comes from."""

from __future__ import annotations

import itertools
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from shared.protocol import ErrorCode, ProtocolError


@dataclass
class Request:
    """A validated inference request inside the executor."""

    id: str
    robot: str
    model: str
    images: np.ndarray  # uint8 [cameras, H, W, 3]
    state: np.ndarray  # float32 [state_dim]
    tokens: np.ndarray  # int64 [prompt_len]
    arrival: float  # time.monotonic() when the executor received it
    deadline: float  # time.monotonic() by which the reply is due
    envelope: Any = None  # reply route, owned by the I/O layer
    noise: np.ndarray | None = None  # fixed initial noise [horizon, action_dim]; drawn by the engine when None


@dataclass
class Result:
    request: Request
    actions: np.ndarray | None = None  # float32 [horizon, action_dim]
    error: tuple[ErrorCode, str] | None = None
    admitted: float = 0.0  # when its batch entered the VLM stage
    vlm_s: float = 0.0
    action_s: float = 0.0
    done: float = field(default_factory=time.monotonic)
    lockstep: int = -1  # index of the lockstep that ran its VLM stage (lockstep engines)


def batch_size_for(pending: int, max_batch: int) -> int:
    """Largest power of two not above min(pending, max_batch): the sizes graphs exist for."""
    n = min(pending, max_batch)
    return 1 << (n.bit_length() - 1) if n > 0 else 0


class EarliestSLOFirst:
    """Serve the queue whose head request has the least time left before its deadline."""

    name = "esf"

    def pick(self, queues: dict[str, deque[Request]], commit: bool = True) -> str:
        return min((q[0].deadline, name) for name, q in queues.items() if q)[1]


class RoundRobin:
    name = "rr"

    def __init__(self) -> None:
        self._last = ""

    def pick(self, queues: dict[str, deque[Request]], commit: bool = True) -> str:
        names = sorted(queues)
        start = names.index(self._last) + 1 if self._last in queues else 0
        for i in range(len(names)):
            name = names[(start + i) % len(names)]
            if queues[name]:
                if commit:
                    self._last = name
                return name
        raise LookupError("no pending request")


class LargestQueueFirst:
    name = "lqf"

    def pick(self, queues: dict[str, deque[Request]], commit: bool = True) -> str:
        # Ties go to the older head, so a queue cannot starve behind an equal-length one.
        return min((-len(q), q[0].arrival, name) for name, q in queues.items() if q)[2]


POLICIES = {"esf": EarliestSLOFirst, "rr": RoundRobin, "lqf": LargestQueueFirst}


class ServiceTimes:
    """Recent service times of one model (its batch entering the VLM stage -> its reply), for shedding
    requests that can no longer make their deadline. A high quantile of a short window: it follows the
    engine's current lockstep length (which co-located models and batch sizes change) and is rarely below
    what a request taken now will take.

    Measurements expire, each ``STALE_S`` after it was taken: an estimate above the model's whole deadline (after a
    stall, a reload, a burst of slow locksteps) would shed every request, so no batch would run and nothing would
    ever lower it. The window as a whole used to expire only after ``STALE_S`` without any reply, so the trickle of
    requests a too-high estimate still let through kept it alive: after a slow burst, nine in ten requests that could
    make a 50 ms deadline were shed for about 5 s. The newest ``MIN_SAMPLES`` count whatever their age while replies
    keep coming: of a handful, the 90th percentile is the slowest, and one slow batch at 5 batches a second shed
    requests that could make it for a whole second."""

    WINDOW = 64
    QUANTILE = 0.9
    STALE_S = 1.0
    MIN_SAMPLES = 16

    def __init__(self) -> None:
        self._recent: deque[tuple[float, float]] = deque(maxlen=self.WINDOW)  # (when, seconds)

    def note(self, seconds: float, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        if self._recent and now - self._recent[-1][0] > self.STALE_S:  # after a gap without replies: start afresh
            self._recent.clear()
        self._recent.append((now, seconds))

    def clear(self) -> None:
        self._recent.clear()

    def estimate(self, now: float | None = None) -> float:
        """The quantile of the measurements younger than STALE_S (at least the newest MIN_SAMPLES); 0 when the newest
        is older than that, or there is none. Reads only (the scheduler's side-effect-free peek asks it too)."""
        now = time.monotonic() if now is None else now
        if not self._recent or now - self._recent[-1][0] > self.STALE_S:
            return 0.0
        n = max(self.MIN_SAMPLES, sum(1 for t, _ in self._recent if now - t <= self.STALE_S))
        fresh = sorted(s for _, s in list(self._recent)[-n:])
        return fresh[min(len(fresh) - 1, int(self.QUANTILE * len(fresh)))]


def _cannot_make_it(req: Request, now: float, service_s: float) -> bool:
    """Its deadline is nearer than the recent service time, which is itself shorter than the request's
    whole budget. An estimate that no request could beat (a slow burst measured it) sheds nothing: the
    requests then run, are measured, and bring it back down; shedding them all would keep it there."""
    return now + service_s >= req.deadline and service_s < req.deadline - req.arrival


class ModelQueues:
    """One bounded FIFO per co-located model, shared by the I/O thread and the engine thread."""

    def __init__(self, models: list[str], max_queue: int = 256, policy: str = "esf", shed_expired: bool = True,
                 shed_late: bool = False):
        if policy not in POLICIES:
            raise ValueError(f"unknown queue policy {policy!r}; known: {', '.join(POLICIES)}")
        self._queues: dict[str, deque[Request]] = {m: deque() for m in models}
        self._max_queue = max_queue
        self._policy = POLICIES[policy]()
        self._shed_expired = shed_expired or shed_late
        # Under overload the head of every queue is a request close to its deadline: served, it finishes late
        # and so does the one behind it (the "domino" of earliest-deadline-first). Shedding the heads that can
        # no longer finish in time keeps the requests that can (docs/engine.md, "Overload").
        self._service = {m: ServiceTimes() for m in models} if shed_late else {}
        self._cond = threading.Condition()
        self._pending = 0
        self._shed: list[Request] = []  # expired requests a full queue gave up at put: answered at the next take
        # Closed once the engine's loop has ended: nothing would ever take a request put then.
        self._closed = False

    def note_service(self, model: str, seconds: float, now: float | None = None) -> None:
        """A batch of ``model`` took ``seconds`` from entering the VLM stage to its results (shed_late)."""
        times = self._service.get(model)
        if times is not None:
            with self._cond:
                times.note(seconds, now)

    def service_estimate(self, model: str, now: float | None = None) -> float:
        times = self._service.get(model)
        if times is None:
            return 0.0
        with self._cond:
            return times.estimate(now)

    @property
    def policy(self) -> str:
        return self._policy.name

    def put(self, req: Request) -> None:
        with self._cond:
            if self._closed:
                raise ProtocolError(ErrorCode.UNAVAILABLE, "the engine has stopped (executor shutting down or "
                                                           "changing its models); retry")
            q = self._queues.get(req.model)
            if q is None:
                raise ProtocolError(ErrorCode.UNKNOWN_MODEL, f"model {req.model!r} is not served by this executor")
            if len(q) >= self._max_queue and self._shed_expired:
                # Full of requests already late (a long lockstep, a stall): those are shed now, not at the next take,
                # or they would turn away requests that can still make it. Late by the new request's arrival: the
                # clock its I/O layer (or a harness's virtual time) stamps requests with.
                while q and q[0].deadline <= req.arrival:
                    self._shed.append(q.popleft())
                    self._pending -= 1
                if self._shed:
                    self._cond.notify()  # the engine answers them at its next take
            if len(q) >= self._max_queue:
                raise ProtocolError(ErrorCode.OVERLOADED, f"queue of {req.model!r} is full ({self._max_queue} requests)")
            q.append(req)
            self._pending += 1
            self._cond.notify()

    def wait(self, timeout: float) -> bool:
        """Block until a request is pending or ``timeout`` passes; True when one is pending."""
        with self._cond:
            if self._pending == 0 and not self._shed:
                self._cond.wait(timeout)
            return self._pending > 0 or bool(self._shed)

    def take(self, max_batch: int, now: float | None = None) -> tuple[str, list[Request], list[Request]]:
        """Pick a queue by the policy and dequeue a power-of-two batch from it.

        Returns (model, batch, expired): requests whose deadline already passed (shed_expired), or
        is nearer than the model's recent service time (shed_late), are taken out and returned
        separately, so they cost no GPU time.
        """
        now = time.monotonic() if now is None else now
        expired: list[Request] = []
        with self._cond:
            for model, n in self._late_heads(now).items():
                q = self._queues[model]
                expired.extend(q.popleft() for _ in range(n))
            self._pending -= len(expired)
            # Those a full queue shed at put left the pending count then.
            expired, self._shed = self._shed + expired, []
            if self._pending == 0:
                return "", [], expired
            model = self._policy.pick(self._queues)
            q = self._queues[model]
            n = batch_size_for(len(q), max_batch)
            batch = [q.popleft() for _ in range(n)]
            self._pending -= n
            return model, batch, expired

    def peek(self, max_batch: int, now: float | None = None) -> tuple[str, list[Request]]:
        """The batch ``take`` would return now if nothing changed (no side effects): lets the
        engine copy the likely next batch's observations while the GPU is busy. Heads ``take``
        would shed are passed over here too: under overload they used to make the copied batch
        another than the one taken, which was then copied again between locksteps."""
        now = time.monotonic() if now is None else now
        with self._cond:
            late = self._late_heads(now)
            queues = self._queues
            if late:
                queues = {m: q if m not in late else deque(itertools.islice(q, late[m], None))
                          for m, q in queues.items()}
            if not any(queues.values()):
                return "", []
            model = self._policy.pick(queues, commit=False)
            q = queues[model]
            return model, [q[i] for i in range(batch_size_for(len(q), max_batch))]

    def _late_heads(self, now: float) -> dict[str, int]:
        """Model -> how many requests at the head of its queue are to be shed at ``now`` (shed_expired: deadline
        passed; shed_late: nearer than the model's recent service time). Models with none are left out."""
        late: dict[str, int] = {}
        if not self._shed_expired:
            return late
        for model, q in self._queues.items():
            times = self._service.get(model)
            est = times.estimate(now) if times is not None else 0.0
            n = 0
            while n < len(q) and (q[n].deadline <= now or _cannot_make_it(q[n], now, est)):
                n += 1
            if n:
                late[model] = n
        return late

    def depths(self) -> dict[str, int]:
        with self._cond:
            return {m: len(q) for m, q in self._queues.items()}

    def drain(self) -> list[Request]:
        """Remove and return everything pending (shutdown: each still gets an answer)."""
        with self._cond:
            out = [r for q in self._queues.values() for r in q] + self._shed
            for q in self._queues.values():
                q.clear()
            self._shed = []
            self._pending = 0
            return out

    def close(self) -> tuple[list[Request], list[Request]]:
        """``drain`` and refuse every later ``put`` (UNAVAILABLE), in one step: the engine's loop has
        ended, so a request queued after its last drain would never be answered (a submit racing a
        reload's stop, or an engine whose loop ended on a fault). Returns (queued, shed): those a full queue
        shed as late and no take has answered yet are DEADLINE_EXCEEDED, not "retry" as the queued are."""
        with self._cond:
            self._closed = True
            shed = list(self._shed)
            self._shed = []
            return self.drain(), shed

    def reopen(self) -> None:
        """Take requests again: an engine loop (re)starts (the capacity harness runs one engine per epoch). The
        service times measured before describe another run: a reused engine shed feasible requests by them."""
        with self._cond:
            self._closed = False
            for times in self._service.values():
                times.clear()
