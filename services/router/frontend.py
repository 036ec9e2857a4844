"""The router's socket loop: robots on one ROUTER socket, executors on another.

Only the small msgpack header of a request is decoded; image frames are forwarded to the
executor untouched. Every request gets exactly one answer: the executor's reply, or an
error from here when the request is malformed, unroutable, or its executor went away or restarted.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from dataclasses import dataclass

import zmq

from services.router.routing import PIN_IDLE_S, Routing
from shared import control
from shared.config import ClusterConfig, dial_address
from shared.control import RoutingTable, TableError
from shared.metrics import RouterMetrics, serve
from shared.protocol import (MAX_ID_CHARS, ErrorCode, Metadata, Pong, ProtocolError, RequestId, check_header, encode,
                             error_frames, header_id, max_frames, message_bytes, shown, unpack_header)
from shared.service import bind, connect, connected_again, keep_alive, monitor_events

log = logging.getLogger("robion.router")

MAX_IN_FLIGHT = 65536
MAX_HELLO_BYTES = 4096  # an executor_hello is under 400 bytes (a name of at most 255 bytes and a 32-char token)
MAX_EXECUTOR_INSTANCES = 4096  # executor names whose process token is remembered (see _executor_hello)
TABLE_POLL_S = 0.1
# One poll is outstanding at a time; an unanswered one is sent again after this long (a control plane that restarted
# never answers the last poll to its predecessor). Polls sent every TABLE_POLL_S whatever came back piled up while the
# plane was busy solving (seconds), and it then answered each with the whole new table, all of which the router decoded
# while robots' requests waited.
TABLE_POLL_RETRY_S = 1.0
PIN_SWEEP_S = 5.0  # how often silent robots' pins are released (routing.PIN_IDLE_S)
SHUTDOWN_LINGER_MS = 1000  # at shutdown, how long the last answers may take to leave
WARN_EVERY_S = 5.0  # refusals a peer can trigger at will are logged at most this often, with a count
# After an executor's connection closes (the socket's monitor names no identity), each executor with requests in flight
# is probed this long, every sweep: one empty frame, which executors ignore. ROUTER_MANDATORY refuses it for an identity
# whose connection is gone. Its requests are answered once it has stayed unreachable for RECONNECT_GRACE_S: a living
# executor whose connection was reset reconnects within libzmq's reconnect interval (0.1 s), still holding its requests,
# and answers them on the new connection.
PROBE_AFTER_DISCONNECT_S = 1.5
RECONNECT_GRACE_S = 0.5
# An executor back on a new connection (its hello says so) still holds the requests it had read; those that were
# queued for it on the old connection are gone. Which is which cannot be told here, so each request from before the
# reconnect's hello was read (one forwarded on the new connection just before counts too) that it has not answered
# this long after is answered UNAVAILABLE (a frozen executor's 60 queued requests waited request_timeout_s, 30 s).
RECONNECT_ANSWER_S = 3.0
# This many restarts of one executor name within FLAPPING_WINDOW_S are reported as two processes sharing the name.
FLAPPING_RESTARTS = 3
FLAPPING_WINDOW_S = 30.0

# A request in flight: (robot, id type, id). The id keeps its wire type, so 7 and "7" from one
# robot are two requests; the type is in the key so that stays true whatever the ids compare as.
FlightKey = tuple[bytes, type, RequestId]


def flight_key(robot: bytes, rid: RequestId) -> FlightKey:
    return (robot, type(rid), rid)


@dataclass
class InFlight:
    executor: str
    model: str
    sent_at: float
    # The model's deadline when the request went out (None: no table yet). Its reply is judged by it: by then an
    # apply may have changed the deadline, or taken the model out of the table.
    deadline_s: float | None = None
    # When to answer it UNAVAILABLE if its executor has not: set when the executor came back on a new connection,
    # which may have lost it (see RECONNECT_ANSWER_S).
    fail_at: float | None = None


class FlightTable(dict[FlightKey, InFlight]):
    """The requests in flight, counted per robot connection as they come and go (router.max_in_flight_per_robot)."""

    def __init__(self) -> None:
        super().__init__()
        self.per_robot: Counter[bytes] = Counter()

    def __setitem__(self, key: FlightKey, flight: InFlight) -> None:
        if key not in self:
            self.per_robot[key[0]] += 1
        super().__setitem__(key, flight)

    def __delitem__(self, key: FlightKey) -> None:
        super().__delitem__(key)
        self._gone(key[0])

    def pop(self, key: FlightKey, *default):
        if key in self:
            self._gone(key[0])
        return super().pop(key, *default)

    def clear(self) -> None:
        super().clear()
        self.per_robot.clear()

    def _gone(self, robot: bytes) -> None:
        self.per_robot[robot] -= 1
        if not self.per_robot[robot]:
            del self.per_robot[robot]  # robots come and go: keep only those with requests in flight


@dataclass
class RateLimitedWarning:
    """One kind of warning a sender can provoke at will: logged once per WARN_EVERY_S, with a count."""

    last: float = float("-inf")
    count: int = 0

    def warn(self, message: str, *args: object) -> None:
        self.count += 1
        now = time.monotonic()
        if now - self.last >= WARN_EVERY_S:
            log.warning(message + " (%d such since the last report)", *args, self.count)
            self.last, self.count = now, 0


class Router:
    def __init__(self, cfg: ClusterConfig, context: zmq.Context | None = None):
        self.cfg = cfg
        self.ctx = context or zmq.Context.instance()
        self.routing = Routing()
        self._configured = frozenset(m.name for m in cfg.models)
        self.in_flight = FlightTable()
        self.stats = {"requests": 0, "replies": 0, "errors": 0}
        self.metrics = RouterMetrics()
        self.metrics.serve_models(self._configured)
        serve(self.metrics.registry, cfg.router.metrics_port)
        limit = cfg.router.max_message_bytes

        self.frontend = self.ctx.socket(zmq.ROUTER)
        # ZMQ_MAXMSGSIZE bounds each *frame*, not the message: a single frame far beyond the
        # limit makes libzmq drop the peer's connection, but libzmq has no cap on the number of
        # frames, so a whole message is only measured after it has been received. Whole
        # messages over the limit, and messages with more frames than their kind can carry,
        # are refused here (TOO_LARGE / BAD_REQUEST) once read; docs/protocol.md says the same.
        self.frontend.setsockopt(zmq.MAXMSGSIZE, 2 * limit + 65536)
        self.frontend.setsockopt(zmq.LINGER, 0)
        self.frontend.setsockopt(zmq.ROUTER_HANDOVER, 1)  # a reconnecting robot keeps its identity
        bind(self.frontend, cfg.router.bind, "router.bind")

        self.backend = self.ctx.socket(zmq.ROUTER)
        # Unreachable executor -> EHOSTUNREACH, full pipe -> EAGAIN (sends are NOBLOCK): an error
        # we answer, never a silent drop and never a blocked loop.
        self.backend.setsockopt(zmq.ROUTER_MANDATORY, 1)
        self.backend.setsockopt(zmq.ROUTER_HANDOVER, 1)
        self.backend.setsockopt(zmq.LINGER, 0)
        # The bound the executors keep on what the router sends them. Without it one peer on this port could hand
        # the router's loop a frame of any size: 1 GB took 0.9 GB of memory, and a stream of them 14 GB.
        self.backend.setsockopt(zmq.MAXMSGSIZE, 2 * limit + 65536)
        keep_alive(self.backend, cfg.router.keepalive_s)  # a frozen executor or a dead host is disconnected
        bind(self.backend, cfg.router.backend, "router.backend")
        # An executor's connection closing (its process crashed or was killed: the OS closes its sockets; or it missed
        # the heartbeats of keep_alive: a frozen process or a dead host) is reported here. Without it its requests in
        # flight waited for the control plane to notice its missing heartbeats (seconds), or, with the plane down too,
        # for request_timeout_s.
        self.backend_events = self.backend.get_monitor_socket(zmq.EVENT_DISCONNECTED)
        self._probe_until = 0.0
        self._unreachable_since: dict[str, float] = {}  # executor -> when a probe first found it gone

        self.ctl = self.ctx.socket(zmq.DEALER)
        self.ctl.setsockopt(zmq.LINGER, 0)
        # Queue polls only to a connected control plane: with it down, a DEALER would queue up to
        # its high-water mark and then block the loop; with IMMEDIATE and NOBLOCK a poll is skipped.
        self.ctl.setsockopt(zmq.IMMEDIATE, 1)
        # Each (re)connect to the control plane is reported here: it may be a restarted plane whose tables
        # count from v1 again, and its v0 is not always seen (executors can register before our first poll).
        self.ctl_events = self.ctl.get_monitor_socket(zmq.EVENT_CONNECTED)
        connect(self.ctl, dial_address(cfg.control.bind, cfg.control.connect))
        self._last_table_poll = 0.0
        self._poll_outstanding = False  # a table_get sent and not answered yet
        self._last_sweep = 0.0
        self._last_pin_sweep = time.monotonic()
        self._too_many_frames = RateLimitedWarning()
        self._executor_full = RateLimitedWarning()
        self._bad_hello = RateLimitedWarning()
        self._bad_reply = RateLimitedWarning()
        self._robot_flooding = RateLimitedWarning()
        self._bad_table = RateLimitedWarning()
        self._bad_control = RateLimitedWarning()
        # Executor name -> the process token its last hello carried: a different one is a restart.
        self._instances: dict[str, str] = {}
        self._connections: dict[str, int | None] = {}  # executor name -> the connection number of its last hello
        self._restarts: dict[str, list[float]] = {}  # executor name -> when it restarted lately (FLAPPING_WINDOW_S)
        self._flapping = RateLimitedWarning()
        # The table kept may be a control plane's that has since restarted (it sent its empty v0, or we
        # reconnected): the new one numbers its tables from v1 again, so its next one is installed whatever its version.
        self._table_outlived_plane = False

    # ------------------------------------------------------------------ loop

    def run(self, stop: threading.Event) -> None:
        poller = zmq.Poller()
        for s in (self.frontend, self.backend, self.ctl, self.ctl_events, self.backend_events):
            poller.register(s, zmq.POLLIN)
        while not stop.is_set():
            now = time.monotonic()
            since = now - self._last_table_poll
            if since >= TABLE_POLL_RETRY_S or (since >= TABLE_POLL_S and not self._poll_outstanding):
                self._last_table_poll = now
                try:
                    # A kept table of a plane that restarted is no version of the new plane's: report none (-1),
                    # or a table of the new plane numbered like the kept one would never be sent.
                    # Its executors are named then too: a restarted plane holds its first table until they are
                    # back, and replicas scaled out beside the config are known to it only this way.
                    if self._table_outlived_plane:
                        ask = {"version": -1, "executors": list(self.routing.table.executors)}
                    else:
                        ask = {"version": self.routing.table.version}
                    self.ctl.send(control.pack("table_get", role="router", **ask), zmq.NOBLOCK)
                    self._poll_outstanding = True
                except zmq.Again:
                    pass  # control plane unreachable or not reading: the next poll asks again
            if now - self._last_sweep >= 0.1:
                self._last_sweep = now
                self._expire(now)
                if now < self._probe_until:
                    self._probe_executors(now)
                else:
                    self._unreachable_since.clear()
            if now - self._last_pin_sweep >= PIN_SWEEP_S:
                self._last_pin_sweep = now
                released = self.routing.release_idle(now)
                if released:
                    log.info("released the executor pins of %d robots silent for %.0f s", released, PIN_IDLE_S)
            for sock, _ in poller.poll(50):
                if sock is self.ctl_events:
                    self._control_connected()
                    continue
                if sock is self.backend_events:
                    if monitor_events(self.backend_events):
                        self._probe_until = time.monotonic() + PROBE_AFTER_DISCONNECT_S
                        self._probe_executors(time.monotonic())
                    continue
                # Drain each ready socket a bounded number of times so one side cannot starve the other.
                for _ in range(256):
                    try:
                        frames = sock.recv_multipart(zmq.NOBLOCK, copy=False)
                    except zmq.Again:
                        break
                    try:
                        if sock is self.frontend:
                            self._from_robot(frames)
                        elif sock is self.backend:
                            self._from_executor(frames)
                        else:
                            self._from_control(frames)
                    except Exception:  # nothing a peer sends may stop the router
                        log.exception("unexpected failure handling a message")
                        if sock is self.frontend:
                            self._answer_fault(frames)
        self.close()

    def close(self) -> None:
        # Every request gets exactly one answer: those still in flight would otherwise be lost with the
        # router and their robots would each wait out their own timeout before retrying.
        self._refuse_unread()
        for (robot, _, rid), f in list(self.in_flight.items()):
            self._reply_error(robot, rid, ErrorCode.UNAVAILABLE, "the router is shutting down", f.model)
        self.in_flight.clear()
        self.metrics.in_flight.set(0)
        # A bounded linger, not 0, so those answers go out before the context terminates (main.py waits
        # for it). It also lets each connection finish the message it is half-way through: with linger 0
        # the pipe is cut mid-message, and a peer dropping its connection at that moment (peers are often
        # stopped together with the router) can trip libzmq 4.3's assertion in session_base clean_pipes
        # (zeromq/libzmq#3442), aborting the process.
        self.ctl.disable_monitor()
        self.ctl_events.close(linger=0)
        self.backend.disable_monitor()
        self.backend_events.close(linger=0)
        self.ctl.close(linger=0)
        for s in (self.backend, self.frontend):
            s.close(linger=SHUTDOWN_LINGER_MS)

    def _refuse_unread(self) -> None:
        """Requests already in the robots' socket, unread, when the router stops: answered UNAVAILABLE ("retry"),
        as those in flight are, rather than left to each robot's timeout."""
        refused = 0
        for _ in range(MAX_IN_FLIGHT):  # bounded: robots may keep sending while this runs
            try:
                frames = self.frontend.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                break
            try:
                header = unpack_header(frames[1].buffer) if len(frames) > 1 else {}
                model = header.get("model") if isinstance(header, dict) else None
                self._reply_error(frames[0].bytes, header_id(header), ErrorCode.UNAVAILABLE,
                                  "the router is shutting down", model if isinstance(model, str) else "")
                refused += 1
            except Exception:  # unreadable: no id to answer to
                log.debug("could not answer an unread message at shutdown", exc_info=True)
        if refused:
            log.info("answered %d requests not read yet UNAVAILABLE: the router is shutting down", refused)

    # ------------------------------------------------------------------ robots

    def _reply_error(self, robot: bytes, rid: RequestId, code: ErrorCode, message: str, model: str = "") -> None:
        self.stats["errors"] += 1
        # Only served model names become label values: robots cannot grow the series count.
        served = self._serves(model)
        self.metrics.requests.labels(model if served else "", code.value.lower()).inc()
        if served:  # an answer without actions: the robot's request failed, whoever failed it
            self.metrics.slo_missed.labels(model).inc()
        self.frontend.send_multipart([robot, *error_frames(rid, code, message)], copy=False)

    def _answer_fault(self, frames: list[zmq.Frame]) -> None:
        """A robot's request whose handling raised is answered INTERNAL ("retry") at once, unless it went on to
        an executor (that one answers it): otherwise its robot would wait out its own timeout for nothing."""
        try:
            robot = frames[0].bytes
            header = unpack_header(frames[1].buffer) if len(frames) > 1 else {}
            rid = header_id(header)
            # The model named, so the answer counts in its SLO series as the router's other answers do (an unserved
            # name is counted under "" by _reply_error).
            model = header.get("model") if header.get("kind") == "infer" else None
            if flight_key(robot, rid) not in self.in_flight:
                self._reply_error(robot, rid, ErrorCode.INTERNAL, "the router failed to handle this request",
                                  model if isinstance(model, str) else "")
        except Exception:  # the answer is best effort: the failure is logged above
            log.debug("could not answer a request whose handling failed", exc_info=True)

    def _serves(self, model: str) -> bool:
        """A model of the cluster: one the routing table lists, or, before any table has come (the control plane
        is starting, holding its first table back, or down since this router started), one of this router's own
        config. Those are unavailable for now ("retry"), not unknown ("never retry")."""
        return self.routing.knows(model) or (self.routing.table.version == 0 and model in self._configured)

    def _from_robot(self, frames: list[zmq.Frame]) -> None:
        robot = frames[0].bytes
        body = frames[1:]
        if not body:
            return self._reply_error(robot, "", ErrorCode.BAD_REQUEST, "empty message")
        try:
            header = unpack_header(body[0].buffer)
        except ProtocolError as exc:
            return self._reply_error(robot, "", exc.code, exc.message)
        rid = header_id(header)  # "" when unusable: the refusal below still reaches the robot
        kind = header.get("kind")
        model = header.get("model")
        # A refused request for a served model counts under it in the SLO series, as the executor's refusals do
        # (_reply_error keeps names it does not serve out of the labels).
        label = model if kind == "infer" and isinstance(model, str) else ""
        try:
            check_header(header)  # v and id, for every kind
        except ProtocolError as exc:
            return self._reply_error(robot, rid, exc.code, exc.message, label)
        info = self.routing.table.models.get(model) if label else None
        most = max_frames(kind, len(info.cameras) if info is not None else None)
        if len(body) > most:
            # libzmq cannot cap frames per message (see __init__), so this is where a message
            # made of many frames, each under the transport's per-frame limit, is refused.
            self._too_many_frames.warn("refused a %s message of %d frames from robot %r (at most %d)",
                                       shown(kind), len(body), robot, most)
            return self._reply_error(robot, rid, ErrorCode.BAD_REQUEST,
                                     f"message has {len(body)} frames; a {shown(kind)} message has at most {most}",
                                     label)
        size = message_bytes([f.buffer for f in body])
        if size > self.cfg.router.max_message_bytes:
            return self._reply_error(robot, rid, ErrorCode.TOO_LARGE,
                                     f"message is {size} bytes; the limit is {self.cfg.router.max_message_bytes}",
                                     label)
        if kind == "hello":
            table = self.routing.table
            self.metrics.requests.labels("", "ok").inc()  # as the refusals of hellos and pings are counted
            self.frontend.send_multipart([robot, *encode(Metadata(id=rid, models=table.models))], copy=False)
            return
        if kind == "ping":
            self.metrics.requests.labels("", "ok").inc()
            self.frontend.send_multipart([robot, *encode(Pong(id=rid))], copy=False)
            return
        if kind != "infer":
            return self._reply_error(robot, rid, ErrorCode.BAD_REQUEST, f"kind: unknown message kind {shown(kind)}")
        if not isinstance(model, str):
            return self._reply_error(robot, rid, ErrorCode.BAD_REQUEST, "model: expected str")
        if rid == "":
            return self._reply_error(robot, rid, ErrorCode.BAD_REQUEST, "id: expected a non-empty str or int", model)
        if not self._serves(model):
            return self._reply_error(robot, rid, ErrorCode.UNKNOWN_MODEL, f"model {model!r} is not served")
        key = flight_key(robot, rid)
        if key in self.in_flight:
            return self._reply_error(robot, rid, ErrorCode.BAD_REQUEST, f"id: request {rid!r} is already in flight",
                                     model)
        if len(self.in_flight) >= MAX_IN_FLIGHT:
            return self._reply_error(robot, rid, ErrorCode.OVERLOADED, "too many requests in flight", model)
        most = self.cfg.router.max_in_flight_per_robot
        if self.in_flight.per_robot[robot] >= most:
            self._robot_flooding.warn("robot %r has %d requests in flight (router.max_in_flight_per_robot): refusing "
                                      "more", robot, most)
            return self._reply_error(robot, rid, ErrorCode.OVERLOADED,
                                     f"this robot has {most} requests in flight, the most it may have", model)
        self.stats["requests"] += 1
        full: list[str] = []
        # A robot is pinned by its name, not its connection: two clients of one robot (and one restarted with a
        # new socket identity) keep their executor and count once against its quota. A name that is no short
        # string (the executor refuses one that is no string at all) leaves the connection to stand in for it, so
        # the pin table's keys stay as small as identities.
        name = header.get("robot")
        pin = name.encode() if isinstance(name, str) and 0 < len(name) <= MAX_ID_CHARS else robot
        for executor in self.routing.candidates(model, pin):
            try:
                # NOBLOCK: an executor that stops reading (stalled, stopped, swamped) fills its pipe,
                # and a blocking send would freeze this one loop for every robot and table update.
                self.backend.send_multipart([executor.encode(), robot, *body], flags=zmq.NOBLOCK, copy=False)
            except zmq.Again:  # its pipe is at the high-water mark: it is not keeping up
                full.append(executor)
                continue
            except zmq.ZMQError as exc:
                if exc.errno == zmq.EHOSTUNREACH:  # registered but not connected to us (yet / any more)
                    continue
                raise
            # info: the table's entry for the model as the request arrived (above), before it went out.
            self.in_flight[key] = InFlight(executor, model, time.monotonic(),
                                           info.deadline_ms / 1e3 if info is not None else None)
            self.metrics.in_flight.set(len(self.in_flight))
            return
        if full:
            # A host exists but is not taking requests: "retry later", the executor-queue-full answer.
            self._executor_full.warn("executors %s for %r are not reading (queue at the router full)", full, model)
            return self._reply_error(robot, rid, ErrorCode.OVERLOADED,
                                     f"the executors for {model!r} are not taking requests (queue full)", model)
        self._reply_error(robot, rid, ErrorCode.UNAVAILABLE, f"no executor for {model!r} is reachable", model)

    # ------------------------------------------------------------------ executors

    def _from_executor(self, frames: list[zmq.Frame]) -> None:
        if len(frames) < 3:
            return
        robot = frames[1].bytes
        body = frames[2:]
        if not robot:  # an executor's own message (hello on connect and on each registration)
            return self._executor_hello(frames[0].bytes, body[0].buffer)
        try:
            header = unpack_header(body[0].buffer)
        except ProtocolError:
            return self._bad_reply.warn("executor %r sent an undecodable reply header", frames[0].bytes)
        rid = header_id(header)
        key = flight_key(robot, rid)
        flight = self.in_flight.get(key)
        # Only the executor the request went to answers it. Once the router has answered a request itself
        # (timed out, executor gone from the table), the robot may send another under the same id, which can
        # go to another executor; the first one's late answer is for the older observation.
        if flight is None or flight.executor.encode() != frames[0].bytes:
            return  # already answered (timed out or executor declared gone), or not by this executor
        del self.in_flight[key]
        self.stats["replies"] += 1
        status = "ok" if header.get("kind") == "reply" else str(header.get("code", "internal")).lower()
        self.metrics.requests.labels(flight.model, status).inc()
        self.metrics.in_flight.set(len(self.in_flight))
        took = time.monotonic() - flight.sent_at
        met = status == "ok" and (flight.deadline_s is None or took <= flight.deadline_s)
        (self.metrics.slo_met if met else self.metrics.slo_missed).labels(flight.model).inc()
        if status == "ok":
            self.metrics.latency.labels(flight.model).observe(took)
        self.frontend.send_multipart([robot, *body], copy=False)

    def _expire(self, now: float) -> None:
        timeout = self.cfg.router.request_timeout_s
        stale = [k for k, f in self.in_flight.items()
                 if now - f.sent_at > timeout or (f.fail_at is not None and now >= f.fail_at)]
        for key in stale:
            f = self.in_flight.pop(key)
            robot, _, rid = key
            why = (f"executor {f.executor} did not answer within {timeout} s" if f.fail_at is None or now < f.fail_at
                   else f"executor {f.executor} reconnected and did not answer it: lost with its old connection")
            self._reply_error(robot, rid, ErrorCode.UNAVAILABLE, why, f.model)
        if stale:
            self.metrics.in_flight.set(len(self.in_flight))

    def _probe_executors(self, now: float) -> None:
        """Fail the requests in flight to each executor whose connection has been gone for RECONNECT_GRACE_S (see
        PROBE_AFTER_DISCONNECT_S)."""
        for executor in {f.executor for f in self.in_flight.values()}:
            try:
                self.backend.send_multipart([executor.encode(), b""], flags=zmq.NOBLOCK)
            except zmq.Again:
                pass  # connected, its pipe full: a stalled executor is request_timeout_s's to answer for
            except zmq.ZMQError as exc:
                if exc.errno != zmq.EHOSTUNREACH:
                    raise
                if now - self._unreachable_since.setdefault(executor, now) >= RECONNECT_GRACE_S:
                    del self._unreachable_since[executor]
                    self._fail_executor(executor, "closed its connection")
                continue
            self._unreachable_since.pop(executor, None)  # connected (again)

    def _fail_executor(self, executor: str, reason: str = "went away") -> None:
        """Answer every request in flight to ``executor`` UNAVAILABLE: it will never answer them."""
        lost = [k for k, f in self.in_flight.items() if f.executor == executor]
        for key in lost:
            f = self.in_flight.pop(key)
            robot, _, rid = key
            self._reply_error(robot, rid, ErrorCode.UNAVAILABLE, f"executor {executor} {reason}", f.model)
        if lost:
            self.metrics.in_flight.set(len(self.in_flight))
            log.warning("executor %s %s with %d requests in flight: answered them UNAVAILABLE", executor, reason,
                        len(lost))

    def _executor_hello(self, identity: bytes, frame: memoryview) -> None:
        """executor_hello {executor, instance}: a new instance under a known name is a restarted executor.

        The backend socket has ROUTER_HANDOVER, so a new process with the old one's name simply takes
        the name over and the socket gives no sign of it; the old process's requests would otherwise
        wait out request_timeout_s. A request forwarded between the new process's connect and its
        hello went to the new process and is failed with the old ones: at worst a retryable
        UNAVAILABLE (the new process's answer is then dropped as already answered).
        """
        if len(frame) > MAX_HELLO_BYTES:  # decoded whole before its shape is checked: 16 MB took the loop 3-4 s
            return self._bad_hello.warn("ignored a hello of %d bytes from executor %r", len(frame), identity)
        try:
            msg = control.unpack(frame)
            name = identity.decode()
        except (ProtocolError, UnicodeDecodeError) as exc:
            return self._bad_hello.warn("ignored an unreadable message from executor %r: %s", identity, exc)
        instance = msg.get("instance")
        if (msg.get("kind") != "executor_hello" or msg.get("executor", name) != name
                or not (instance is None or (isinstance(instance, str) and instance))):
            return self._bad_hello.warn("ignored a malformed hello from executor %r: kind %s, executor %s, instance %s",
                                        identity, shown(msg.get("kind")), shown(msg.get("executor")), shown(instance))
        if instance is None:
            return  # an executor from before the instance field: a restart cannot be told
        connection = msg.get("connection")
        connection = connection if isinstance(connection, int) and not isinstance(connection, bool) else None
        known = self._instances.get(name)
        if known == instance:
            # The same process again (it says hello each heartbeat). On a new connection of its own (a reset, or a
            # heartbeat timeout after a freeze), what was queued for it on the old one is gone with it: its requests
            # from before still unanswered RECONNECT_ANSWER_S later are failed, not left to request_timeout_s.
            last = self._connections.get(name)
            self._connections[name] = connection
            if connection is not None and last is not None and connection != last:
                self._mark_lost_unless_answered(name)
            return
        if known is None and len(self._instances) >= MAX_EXECUTOR_INSTANCES:
            # peers inventing names: forget them rather than grow without bound
            self._instances.clear()
            self._connections.clear()
            self._restarts.clear()
        self._instances[name] = instance
        self._connections[name] = connection
        if known is None:
            return  # the first hello of the name this router has seen: nothing to compare with
        log.info("executor %s restarted (instance %s -> %s)", name, known, instance)
        # Two live processes under one name take it from each other whenever one redials (the heartbeats find the
        # connection the other took), so each passes for the other's restart every few seconds. Which of them should
        # serve cannot be told here (a process that was frozen, a successor that has since died): say so instead.
        now = time.monotonic()
        recent = [t for t in self._restarts.get(name, []) if now - t < FLAPPING_WINDOW_S] + [now]
        self._restarts[name] = recent
        if len(recent) >= FLAPPING_RESTARTS:
            self._flapping.warn("executor %s restarted %d times in %.0f s: two processes may be running under this "
                                "name (each taking it from the other: stop one), or it is crash-looping", name,
                                len(recent), FLAPPING_WINDOW_S)
        self._fail_executor(name, "restarted")

    def _mark_lost_unless_answered(self, executor: str) -> None:
        fail_at = time.monotonic() + RECONNECT_ANSWER_S
        marked = 0
        for flight in self.in_flight.values():
            if flight.executor == executor and flight.fail_at is None:
                flight.fail_at = fail_at
                marked += 1
        if marked:
            log.info("executor %s reconnected with %d requests in flight: those it does not answer within %.0f s are "
                     "answered UNAVAILABLE", executor, marked, RECONNECT_ANSWER_S)

    # ------------------------------------------------------------------ control plane

    def _control_connected(self) -> None:
        """A (re)connect to the control plane: the table kept may be an earlier plane's, so report none
        (-1) and install the plane's next table whatever its number. A v0 alone did not tell: a restarted
        plane past v0 by our first poll, numbering a table like the kept one, was never asked for it."""
        if connected_again(self.ctl_events):
            self._table_outlived_plane = True

    def _from_control(self, frames: list[zmq.Frame]) -> None:
        # The control plane answers each poll (ten a second) the same way until it is fixed, so what
        # cannot be read is reported rate-limited and without a traceback, and the current table kept.
        self._poll_outstanding = False  # the router sends the plane nothing but polls: this answers the last one
        try:
            msg = control.unpack(frames[-1].buffer)
        except ProtocolError as exc:
            return self._bad_control.warn("ignored an unreadable message from the control plane: %s", exc.message)
        if msg.get("kind") == "table" and msg.get("table") is not None:
            try:
                table = RoutingTable.from_wire(msg["table"])
            except TableError as exc:
                return self._bad_table.warn("kept routing table v%d: the control plane sent an unreadable one: %s",
                                            self.routing.table.version, exc)
            if table.version == 0 and self.routing.table.version != 0:
                # Version 0 is a control plane's table before any executor has registered: nothing in it. One
                # that restarted starts there again; installing it would answer every request UNKNOWN_MODEL
                # ("do not retry") and fail those in flight until the executors register again.
                self._table_outlived_plane = True
                return self._bad_table.warn("kept routing table v%d: the control plane sent its empty table v0 "
                                            "(it restarted?)", self.routing.table.version)
            if table.version != self.routing.table.version or self._table_outlived_plane:
                self._table_outlived_plane = False
                gone = self.routing.update(table)
                self.metrics.table_version.set(table.version)
                self.metrics.executors.set(len({e for ex in table.routes.values() for e in ex}))
                self.metrics.serve_models(table.models)
                log.info("routing table v%d: %s", table.version,
                         {m: e for m, e in table.routes.items()})
                for executor in gone:
                    self._fail_executor(executor)
