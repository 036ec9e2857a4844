"""Robot SDK: talk to a Robion router over a ZeroMQ DEALER socket.

    client = RobotClient("tcp://server:5555", robot_id="arm-07")
    info = client.metadata()["pi0-libero"]
    actions = client.infer("pi0-libero", {"cam0": img0, "cam1": img1}, state, "pick up the cup").actions

``infer`` blocks; ``submit`` + ``poll`` (or ``wait_any`` over many clients) let one process
drive many robots without threads. Every request gets exactly one outcome: its reply, or
RequestTimeout once it is older than the client's ``timeout_s`` (``poll`` reports that too).
"""

from __future__ import annotations

import itertools
import logging
import math
import time
import uuid
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Iterable, Mapping, Sequence

import numpy as np
import zmq

from shared.protocol import (MAX_HEADER_BYTES, MAX_ID_CHARS, ErrorCode, ErrorReply, Hello, InferReply, InferRequest,
                             Metadata, ModelInfo, Ping, Pong, ProtocolError, RequestId, Timings, decode, encode,
                             header_id, message_bytes, unpack_answer_header, valid_id)
from shared.service import connect

log = logging.getLogger("robion.client")

# The generated ids are "<robot_id>-<session>-<counter>" or "<robot_id>-<session>-<tag>-<counter>"; this leaves
# room for the 8-character session, a tag and a 20-digit counter, so an id the client makes is always one the
# router accepts (at most MAX_ID_CHARS characters).
MAX_ROBOT_ID_CHARS = MAX_ID_CHARS - 48
MAX_IDENTITY_BYTES = 255  # ZeroMQ's limit on a socket identity
# Ids given up on (RequestTimeout, an interrupted wait) whose late answer has not come: at most this many are
# remembered, the oldest forgotten first. A router answers every request it forwarded within its
# request_timeout_s, so the set stays small unless the router restarts with answers owed.
MAX_ABANDONED_IDS = 65536
MAX_WHY_CHARS = 1024  # a decoder message can quote a peer's string (a dtype, a kind): keep the error readable
# Requests waiting to be written to the router's connection. A robot has a few in flight; more than this queued
# means the connection is not draining, and a request that old is better refused now than sent late.
SEND_QUEUE = 64

# The answer each request expects, besides an error reply; its wire kind names it in a MalformedReply.
ANSWER_KINDS: dict[type, str] = {InferReply: "reply", Metadata: "metadata", Pong: "pong"}


class RobionError(Exception):
    """A request failed; ``code`` is one of shared.protocol.ErrorCode.

    Raised as is for the server's error reply; the subclasses below are outcomes the SDK decides.
    """

    def __init__(self, code: ErrorCode, message: str, request_id: str = ""):
        super().__init__(f"{code.value}: {message}")
        self.code = code
        self.message = message
        self.request_id = request_id


class RequestTimeout(RobionError, TimeoutError):
    """No reply arrived in time."""

    def __init__(self, request_id: str, timeout_s: float):
        super().__init__(ErrorCode.UNAVAILABLE, f"no reply within {timeout_s:.3f} s", request_id)


class MalformedReply(RobionError):
    """The request's answer arrived but cannot be used: garbled past its header, or not an answer to it.

    The request fails at once rather than at its timeout, so a controller learns without waiting that
    no actions are coming. INTERNAL: a fault on the serving side, and the request may be retried.
    """

    def __init__(self, request_id: RequestId, why: str):
        if len(why) > MAX_WHY_CHARS:
            why = why[:MAX_WHY_CHARS] + "..."
        super().__init__(ErrorCode.INTERNAL, f"malformed reply: {why}", request_id)


@dataclass
class Completion:
    """The outcome of one submitted request."""

    request_id: str
    model: str
    sent_at: float  # time.monotonic() at send
    received_at: float
    actions: np.ndarray | None = None
    timings: Timings = field(default_factory=Timings)
    error: RobionError | None = None
    request_bytes: int = 0
    reply_bytes: int = 0

    @property
    def latency_s(self) -> float:
        return self.received_at - self.sent_at

    @property
    def ok(self) -> bool:
        return self.error is None


def _float32_state(state: np.ndarray) -> np.ndarray:
    """The state as the wire's float32. A complex state lost its imaginary part in the cast, silently, and finite
    values beyond float32's range became infinities the server refused as "NaN or infinity": both are ValueErrors
    (BAD_REQUEST) here, saying which."""
    given = np.asarray(state)
    if np.iscomplexobj(given):
        raise ValueError(f"state: expected real numbers, got {given.dtype}")
    with np.errstate(over="ignore"):
        out = given.astype(np.float32)
        # Python ints past int64 come as an object array: float64 holds them (or raises OverflowError) and tells
        # a value too large for float32 from one that was NaN or infinite to begin with.
        if not np.isfinite(out).all() and np.isfinite(given.astype(np.float64)).all():
            raise ValueError("state: a value is beyond float32's range (about 3.4e38)")
    return out


def _check_timeout(name: str, value: float) -> float:
    """A timeout in seconds: a number, not NaN (which no clock comparison ever ends), not negative."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value) or value < 0:
        raise RobionError(ErrorCode.BAD_REQUEST, f"{name}: expected seconds >= 0 (math.inf: no limit), got {value!r}")
    return float(value)


class RobotClient:
    """One robot's connection. Not thread-safe (one ZeroMQ socket); use one client per thread.

    Requests go out only over a live connection to the router, never queued to reach it late, after their
    caller gave up on them. While there is none (the router not started yet, restarting, unreachable),
    ``submit`` fails at once with ``UNAVAILABLE`` (a new client gives its first connection up to
    ``connect_timeout_s``), and a blocking call waits for one within its timeout, then fails so.
    """

    def __init__(self, address: str, robot_id: str | None = None, timeout_s: float = 10.0,
                 context: zmq.Context | None = None, connect_timeout_s: float = 1.0):
        self.robot_id = robot_id or f"robot-{uuid.uuid4().hex[:8]}"
        # The router tells requests apart by (identity, id) and gives a reconnecting identity's replies to the new
        # connection, and its request_timeout_s outlasts ours: a client replacing another under the same robot_id
        # (a restarted robot, a new client after a timeout) must not reuse its ids, or it is refused "already in
        # flight" or handed the actions of the old client's request. Hence a per-client session in every id.
        self._session = uuid.uuid4().hex[:8]
        # The socket identity is the session's too: two clients of one robot (a thread each) under one identity
        # would share one connection at the router, which hands every reply to the newer (ROUTER_HANDOVER), and
        # the older would time out on all of its requests. The router routes a robot by the request's `robot`.
        identity = f"{self.robot_id}-{self._session}".encode()
        # Checked before the socket exists: a refused identity used to raise from setsockopt and leave an
        # open socket behind, which makes the context's term() wait forever.
        if len(self.robot_id) > MAX_ROBOT_ID_CHARS or len(identity) > MAX_IDENTITY_BYTES:
            raise ValueError(f"robot_id: at most {MAX_ROBOT_ID_CHARS} characters and {MAX_IDENTITY_BYTES - 9} bytes "
                             f"in UTF-8, got {len(self.robot_id)} characters")
        try:
            self.timeout_s = _check_timeout("timeout_s", timeout_s)
            connect_timeout_s = _check_timeout("connect_timeout_s", connect_timeout_s)
        except RobionError as exc:
            raise ValueError(exc.message) from None
        self._ctx = context or zmq.Context.instance()
        self.socket = self._ctx.socket(zmq.DEALER)
        try:
            self.socket.setsockopt(zmq.LINGER, 0)
            self.socket.setsockopt(zmq.IDENTITY, identity)
            # IMMEDIATE: queue only to a connected router. Without it a request sent while the router is away
            # waits in the socket and reaches the router when it is back, long after poll() reported it timed
            # out, and costs GPU time then; tens of them held hundreds of MB of camera images meanwhile.
            self.socket.setsockopt(zmq.IMMEDIATE, 1)
            self.socket.setsockopt(zmq.SNDHWM, SEND_QUEUE)
            connect(self.socket, address)
        except zmq.ZMQError:
            self.socket.close(linger=0)
            raise
        self._ids = itertools.count()
        # id -> (model, sent_at, bytes, the answer's type). In send order, hence in sent_at order (a request
        # is added once, when it goes out): the oldest, the next to expire, is always the first.
        self._pending: dict[RequestId, tuple[str, float, int, type]] = {}
        # Outcomes a blocking call read off the socket while it waited for its own, in arrival order, until poll()
        # returns them. A list, not a map by id: an id may be used again once answered, and each request's
        # outcome must still come out once.
        self._done: list[Completion] = []
        # Ids whose request was given up on before its answer came (in give-up order). The answer may still come:
        # sent again under one of these ids, a request would be paired with the older request's actions,
        # computed for another observation. So such an id is refused until that late answer has arrived.
        self._abandoned: OrderedDict[RequestId, None] = OrderedDict()
        self._metadata: dict[str, ModelInfo] | None = None
        # Until then a send waits for the first connection, which comes up a moment after connect() returns.
        self._connect_by = time.monotonic() + connect_timeout_s

    # -- non-blocking API

    def submit(self, model: str, images: Mapping[str, np.ndarray] | Sequence[np.ndarray], state: np.ndarray,
               instruction: str = "", request_id: RequestId | None = None) -> RequestId:
        """Send a request and return its id (``request_id``, or one the client makes); collect the outcome with
        ``poll``. The arrays are copied as the request goes out, so they may be reused at once.

        Images given as a list are matched to the model's camera names, which the first such call fetches with
        ``metadata()`` (one round trip, at most ``timeout_s``); a mapping by camera name never waits.
        """
        return self._submit(model, images, state, instruction, request_id, self.timeout_s, blocking=False)

    def _submit(self, model: str, images: Mapping[str, np.ndarray] | Sequence[np.ndarray], state: np.ndarray,
                instruction: str, request_id: RequestId | None, timeout_s: float, blocking: bool) -> RequestId:
        deadline = time.monotonic() + timeout_s
        if not isinstance(images, Mapping):
            cams = self._camera_names(model, len(images), timeout_s)
            images = dict(zip(cams, images))
        # `is None`, not `or`: 0 (and "", refused below) are the caller's ids, not a request for a generated one.
        rid = request_id if request_id is not None else f"{self.robot_id}-{self._session}-{next(self._ids)}"
        try:
            frames = encode(InferRequest(id=rid, robot=self.robot_id, model=model, images=dict(images),
                                         state=_float32_state(state), instruction=instruction))
        except (TypeError, ValueError, OverflowError) as exc:
            # A dtype that cannot travel, text that is no UTF-8 (lone surrogates), an int id past 64 bits.
            raise RobionError(ErrorCode.BAD_REQUEST, str(exc), str(rid)) from None
        # A blocking call may wait for a connection as long as for its answer; submit only for a new client's first.
        left = deadline - time.monotonic()
        self._send(rid, model, frames, InferReply, left if blocking else min(left, self._connect_by - time.monotonic()))
        return rid

    def poll(self, timeout_s: float = 0.0) -> list[Completion]:
        """Completions that arrived within ``timeout_s`` (0: only those already here).

        A submitted request still unanswered ``self.timeout_s`` after it was sent is completed here with a
        RequestTimeout error (code UNAVAILABLE), and a reply for it that comes later is dropped: each
        request gets exactly one outcome, and ``pending()`` reaches 0 even when no reply ever comes.
        """
        # A blocking call (infer, ping, metadata) reads every reply off the shared socket while it waits
        # for its own and keeps the others in _done; they are this poll's results, returned first. With
        # any in hand, poll only gathers what else is already here and does not wait.
        deadline = time.monotonic() + _check_timeout("timeout_s", timeout_s)
        out, self._done = self._done, []
        if self.socket.closed:  # close() ended every request in flight; their outcomes are in out
            return out
        while True:
            # Replies already here first: a request whose reply has come is not one to give up on.
            while self.socket.poll(0):
                done = self._receive_one()
                if done is not None:
                    out.append(done)
            now = time.monotonic()
            out.extend(self._expire(now))
            if out or now >= deadline:
                return out
            # Wait for a reply, but no longer than until the next request expires.
            wake = deadline
            expiry = self._next_expiry()
            if expiry is not None:
                wake = min(wake, expiry)
            self.socket.poll(None if math.isinf(wake) else max(1, math.ceil((wake - now) * 1000)))

    def pending(self) -> int:
        """Submitted requests whose outcome ``poll`` has not returned yet.

        Outcomes a blocking call already read off the socket are counted until ``poll`` returns them, so
        ``while client.pending(): client.poll(...)`` never stops with results left behind. A request no
        reply ever comes for counts until ``poll`` reports its RequestTimeout, ``timeout_s`` after its send.
        """
        return len(self._pending) + len(self._done)

    # -- blocking API

    def infer(self, model: str, images: Mapping[str, np.ndarray] | Sequence[np.ndarray], state: np.ndarray,
              instruction: str = "", timeout_s: float | None = None) -> Completion:
        """Send one request and wait for its action chunk; raises RobionError / RequestTimeout. ``timeout_s``
        (default: the client's) bounds the whole call, a first fetch of the camera names included."""
        timeout_s = self.timeout_s if timeout_s is None else _check_timeout("timeout_s", timeout_s)
        deadline = time.monotonic() + timeout_s
        rid = self._submit(model, images, state, instruction, None, timeout_s, blocking=True)
        done = self._wait_for(rid, deadline - time.monotonic(), reported_s=timeout_s)
        if done.error is not None:
            raise done.error
        return done

    def metadata(self, refresh: bool = False, timeout_s: float | None = None) -> dict[str, ModelInfo]:
        """The served models: their camera names, image shape, state size, output shape and deadline."""
        if self._metadata is None or refresh:
            self._round_trip(Hello, Metadata, "hello", timeout_s)
        assert self._metadata is not None
        return self._metadata

    def ping(self, timeout_s: float | None = None) -> float:
        """Round-trip time to the router in seconds."""
        return self._round_trip(Ping, Pong, "ping", timeout_s).latency_s

    def _round_trip(self, message: type, answer: type, tag: str, timeout_s: float | None) -> Completion:
        """Send a message that carries only an id and wait for its answer; its error is raised."""
        timeout_s = self.timeout_s if timeout_s is None else _check_timeout("timeout_s", timeout_s)
        deadline = time.monotonic() + timeout_s
        rid = f"{self.robot_id}-{self._session}-{tag}-{next(self._ids)}"
        self._send(rid, "", encode(message(id=rid)), answer, timeout_s)
        done = self._wait_for(rid, max(0.0, deadline - time.monotonic()), reported_s=timeout_s)
        if done.error is not None:
            raise done.error
        return done

    def close(self) -> None:
        """Close the connection. Requests still in flight end with ``UNAVAILABLE`` ("client closed"); ``poll``
        returns them (and any other outcome not yet returned), so ``pending()`` reaches 0."""
        now = time.monotonic()
        for rid in list(self._pending):
            self._done.append(self._complete(rid, now, 0, error=RobionError(
                ErrorCode.UNAVAILABLE, "client closed before the answer came", rid)))
        self.socket.close(linger=0)

    def __enter__(self) -> "RobotClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- internals

    def _send(self, rid: RequestId, model: str, frames: list, answer: type, connect_wait_s: float) -> None:
        """Send a request and track it; raise RobionError, with nothing left pending, when it cannot go out.
        Without a connection to the router, one is waited for up to ``connect_wait_s``."""
        # The router answers a request whose id or header it cannot read with id "" (docs/protocol.md): such
        # an answer matches nothing here, so the request would only ever time out. Refuse it before sending.
        # "" included: it is the id of the router's answers to requests it could not read, so a request under
        # it could be handed another request's error.
        if not valid_id(rid) or rid == "":
            raise RobionError(ErrorCode.BAD_REQUEST, f"id: expected a non-empty str of at most {MAX_ID_CHARS} "
                                                     f"characters or an int, got {type(rid).__name__}", "")
        if len(frames[0]) > MAX_HEADER_BYTES:
            raise RobionError(ErrorCode.TOO_LARGE, f"header is {len(frames[0])} bytes; the limit is "
                                                   f"{MAX_HEADER_BYTES} (is the instruction too long?)", str(rid))
        if rid in self._pending:
            raise RobionError(ErrorCode.BAD_REQUEST, f"id: request {rid!r} is already in flight", str(rid))
        if rid in self._abandoned:
            raise RobionError(ErrorCode.BAD_REQUEST, f"id: request {rid!r} timed out and its answer may still "
                                                     f"come; give a retry a fresh id", str(rid))
        if self.socket.closed:
            raise RobionError(ErrorCode.BAD_REQUEST, "the client is closed", str(rid))
        # NOBLOCK: a blocking send would wait until the router is back, past any timeout the caller gave. Waiting
        # here for the connection queues nothing: the request is sent fresh once it is up, or not at all.
        if connect_wait_s > 0:
            self.socket.poll(None if math.isinf(connect_wait_s) else math.ceil(connect_wait_s * 1000), zmq.POLLOUT)
        sent_at = time.monotonic()
        try:
            # copy=True: the frames are views of the caller's arrays, and a zero-copy send reads them only when
            # the message leaves, maybe after a camera loop has written its next image into the same buffer. A
            # copy of a few camera images costs tens of microseconds.
            self.socket.send_multipart(frames, flags=zmq.NOBLOCK, copy=True)
        except zmq.Again:
            raise RobionError(ErrorCode.UNAVAILABLE, "the router is not reachable (no connection, or its send "
                                                     f"queue of {SEND_QUEUE} is full); retry", str(rid)) from None
        self._connect_by = 0.0  # connected once: from now on submit without a connection fails at once
        self._pending[rid] = (model, sent_at, message_bytes(frames), answer)

    def _next_expiry(self) -> float | None:
        """When the oldest request in flight times out (time.monotonic()); None with none in flight."""
        oldest = next(iter(self._pending.values()), None)  # the first is the oldest
        return None if oldest is None else oldest[1] + self.timeout_s

    def _expire(self, now: float) -> list[Completion]:
        """Complete, with RequestTimeout, every request in flight sent ``self.timeout_s`` or longer ago."""
        stale = []
        for rid, (_, sent_at, _, _) in self._pending.items():  # oldest first: stop at the first in time
            if now - sent_at < self.timeout_s:
                break
            stale.append(rid)
        out = [self._complete(rid, now, 0, error=RequestTimeout(rid, self.timeout_s)) for rid in stale]
        for rid in stale:
            self._abandon(rid)
        return out

    def _abandon(self, rid: RequestId) -> None:
        """Remember an id given up on before its answer came, so it is not sent again until that answer has."""
        self._abandoned[rid] = None
        if len(self._abandoned) > MAX_ABANDONED_IDS:
            self._abandoned.popitem(last=False)

    def _camera_names(self, model: str, n: int, timeout_s: float) -> list[str]:
        """The model's camera names, from the cached model list; asked for again once when the cache does not
        fit the call (a model added since, a camera count changed, or a list fetched before the router had
        its routing table), so that an old list never fails a request for good."""
        deadline = time.monotonic() + timeout_s
        cached = self._metadata is not None
        models = self.metadata(timeout_s=timeout_s)
        info = models.get(model)
        if cached and (info is None or len(info.cameras) != n):
            models = self.metadata(refresh=True, timeout_s=max(0.0, deadline - time.monotonic()))
            info = models.get(model)
        if info is None:
            if not models:  # the router has no routing table yet (docs/protocol.md): retryable, as its own answer
                raise RobionError(ErrorCode.UNAVAILABLE, "the router serves no models yet (starting); retry")
            raise RobionError(ErrorCode.UNKNOWN_MODEL, f"model {model!r} is not served")
        if len(info.cameras) != n:
            raise RobionError(ErrorCode.SHAPE_MISMATCH, f"{model} takes {len(info.cameras)} cameras, got {n}")
        return info.cameras

    def _wait_for(self, rid: str, timeout_s: float | None, reported_s: float | None = None) -> Completion:
        """Wait for request ``rid``'s outcome. Whatever ends the wait without one (its timeout, an interrupt)
        ends the request too: a late answer is dropped, never reported by ``poll`` as a completion."""
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout_s
        try:
            while True:
                left = deadline - time.monotonic()
                if left <= 0 or not self.socket.poll(None if math.isinf(left) else int(left * 1000) + 1):
                    raise RequestTimeout(rid, timeout_s if reported_s is None else reported_s)
                done = self._receive_one()
                if done is None:
                    continue
                if done.request_id == rid:
                    return done
                self._done.append(done)  # another request's outcome: poll returns it
        finally:
            if self._pending.pop(rid, None) is not None:  # ended without its answer: it may still come
                self._abandon(rid)

    def _receive_one(self) -> Completion | None:
        """Read one message; the outcome of the request in flight it answers, or None if it answers none."""
        frames = [f.buffer for f in self.socket.recv_multipart(copy=False)]
        now = time.monotonic()
        size = sum(len(f) for f in frames)
        # The header first: its id says which request a reply is for even when the rest is broken, so that
        # request can fail now instead of waiting out its timeout for an answer that has already come.
        try:
            header = unpack_answer_header(frames[0])
        except ProtocolError as exc:
            # No id to read, so no request to fail: the one it answered (if any) runs to its timeout.
            log.debug("dropped a reply whose header cannot be decoded: %s", exc.message)
            return None
        rid = header_id(header)
        try:
            msg = decode(frames, header)
        except Exception as exc:  # ProtocolError, or a fault of the decoder itself: never out of poll()
            why = exc.message if isinstance(exc, ProtocolError) else f"cannot be decoded ({type(exc).__name__})"
            if rid not in self._pending:
                log.debug("dropped a malformed reply for no request in flight (id %.80r): %s", rid, why)
                self._abandoned.pop(rid, None)  # an answer all the same: the id may be used again
                return None
            return self._complete(rid, now, size, error=MalformedReply(rid, why))
        if isinstance(msg, Metadata):
            self._metadata = msg.models  # newer news about the served models, whoever asked
        if rid not in self._pending:
            # Not a request in flight: its caller already got RequestTimeout (one outcome per request), or it
            # is an answer no request of ours can match (id ""). Reporting it would invent a completion. A
            # request given up on has now had its answer, so its id may be used again.
            self._abandoned.pop(rid, None)
            return None
        answer = self._pending[rid][3]
        if isinstance(msg, ErrorReply):
            return self._complete(rid, now, size, error=RobionError(msg.code, msg.message, rid))
        if not isinstance(msg, answer):
            # Well-formed, but no answer to this request (a pong for an infer, a request kind echoed back):
            # as unusable as garbage. Taken for an answer, it used to complete an infer "ok" with no actions.
            return self._complete(rid, now, size, error=MalformedReply(
                rid, f"kind: a {header['kind']!r} message does not answer this request "
                     f"(expected {ANSWER_KINDS[answer]!r} or 'error')"))
        done = self._complete(rid, now, size)
        if isinstance(msg, InferReply):
            done.actions = np.array(msg.actions)  # own the memory: the frame is released after this
            done.timings = msg.timings
        return done

    def _complete(self, rid: RequestId, received_at: float, reply_bytes: int,
                  error: RobionError | None = None) -> Completion:
        """End request ``rid``: it is no longer in flight, and this is its one outcome."""
        model, sent_at, req_bytes, _ = self._pending.pop(rid)
        return Completion(request_id=rid, model=model, sent_at=sent_at, received_at=received_at,
                          request_bytes=req_bytes, reply_bytes=reply_bytes, error=error)


def wait_any(clients: Iterable[RobotClient], timeout_s: float) -> list[tuple[RobotClient, Completion]]:
    """Wait until any client has a completion (or the timeout passes) and collect all that arrived.

    Completions include requests that timed out (RequestTimeout, as ``RobotClient.poll`` reports them):
    the wait ends when the first request in flight on any client expires.
    """
    clients = list(clients)
    end = time.monotonic() + _check_timeout("timeout_s", timeout_s)
    poller = zmq.Poller()
    by_socket = {}
    for c in clients:
        if not c.socket.closed:  # a closed client's outcomes (close() ended its requests) are in its _done
            poller.register(c.socket, zmq.POLLIN)
            by_socket[c.socket] = c

    while True:
        # Nothing is sent or read until the poll below, so each client's next expiry holds until then.
        expiry = {c: c._next_expiry() for c in clients}

        def expired(c: RobotClient, now: float) -> bool:
            return expiry[c] is not None and expiry[c] <= now

        # A client may hold outcomes that a blocking call of it read off the socket already: the socket
        # need not be readable for those, and they are ready now, so do not wait for anything else. Nor
        # for a client with a request past its timeout: that request's outcome is ready too.
        now = time.monotonic()
        ready = [c for c in clients if c._done or expired(c, now)]
        left = end - now
        wait_ms: int | None = None if math.isinf(left) else max(0, math.ceil(left * 1000))  # None: no limit
        soonest = min((e for e in expiry.values() if e is not None and not math.isinf(e)), default=None)
        if soonest is not None:
            until = max(0, math.ceil((soonest - now) * 1000))
            wait_ms = until if wait_ms is None else min(wait_ms, until)
        events = poller.poll(0 if ready else wait_ms)
        readable = {by_socket[sock] for sock, _ in events}
        now = time.monotonic()
        listed = set(ready)
        ready += [c for c in clients if c not in listed and (c in readable or expired(c, now))]
        out: list[tuple[RobotClient, Completion]] = []
        for client in ready:
            out.extend((client, c) for c in client.poll(0))
        # A socket can be readable with nothing to report: a late answer to a request already timed out, or one
        # no request matches, is dropped. That used to end the wait at once, empty, long before its timeout.
        if out or now >= end:
            return out
