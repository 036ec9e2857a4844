"""The executor's I/O thread: requests in from the router, replies out, control-plane heartbeats.

Decoding, validation and tokenisation happen here, off the engine thread, so the engine
only ever sees well-formed requests. Results come back from the engine thread through a
queue plus an inproc wake-up socket (ZeroMQ sockets are not thread-safe).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
import traceback
import uuid
from collections import deque

import numpy as np
import zmq

from services.executor.hosting import EngineSlot, Hosted, ModelStore, ServedInput, free_memory
from services.executor.limits import measure_limits
from services.executor.scheduler import Request, Result
from shared import control
from shared.config import ClusterConfig, ModelConfig, dial_address, settings_digest
from shared.metrics import ExecutorMetrics
from shared.protocol import (ErrorCode, InferReply, InferRequest, ProtocolError, RequestId, Timings, decode,
                             encode, error_frames, header_id, message_bytes, unpack_header)
from shared.service import connect, connection_up, keep_alive, monitor_events

log = logging.getLogger("robion.executor")

# Replies the router's pipe could not take at once (the router is gone or restarting: ZeroMQ queues up to its
# high-water mark, 1000 messages, for a peer that may come back) wait here, in order, and are sent as the pipe
# frees up. Beyond this many the oldest are dropped: a restarted router knows none of their requests, and the
# old one has answered them itself when they timed out.
MAX_UNSENT_REPLIES = 4096


def to_request(msg: InferRequest, served: ServedInput, envelope: bytes, arrival: float) -> Request:
    """Check a decoded request against the model's declared inputs and build the engine's Request."""
    io = served.io
    cams = set(msg.images)
    if cams != set(io.cameras):
        raise ProtocolError(ErrorCode.SHAPE_MISMATCH,
                            f"obs.images: {msg.model} takes cameras {list(io.cameras)}, got {sorted(cams)}")
    for cam in io.cameras:
        img = msg.images[cam]
        if img.dtype != np.uint8 or tuple(img.shape) != tuple(io.image_shape):
            raise ProtocolError(ErrorCode.SHAPE_MISMATCH,
                                f"obs.images.{cam}: expected uint8 {list(io.image_shape)}, got {img.dtype} {list(img.shape)}")
    if msg.state.dtype != np.float32 or msg.state.shape != (io.state_dim,):
        raise ProtocolError(ErrorCode.SHAPE_MISMATCH,
                            f"obs.state: expected float32 [{io.state_dim}], got {msg.state.dtype} {list(msg.state.shape)}")
    if not np.isfinite(msg.state).all():
        raise ProtocolError(ErrorCode.BAD_REQUEST, "obs.state: contains NaN or infinity")
    if len(msg.instruction) > 4096:
        raise ProtocolError(ErrorCode.BAD_REQUEST, "obs.instruction: longer than 4096 characters")
    images = np.stack([msg.images[c] for c in io.cameras])  # copies out of the frames, in camera order
    return Request(id=msg.id, robot=msg.robot, model=msg.model, images=images, state=msg.state.copy(),
                   tokens=served.tokenize(msg.instruction), arrival=arrival, deadline=arrival + served.slo_s,
                   envelope=envelope)


def reply_frames(res: Result, now: float) -> list:
    """The reply to ``res``. A result the engine got wrong (neither actions nor an error, or actions
    that cannot be encoded) is answered INTERNAL, and ``res.error`` says so for the metrics: never
    an ok reply without actions, and never an exception that would end the I/O loop.

    Actions with NaN or infinity (a finite but extreme state overflowing inside the model, a weight
    gone bad) are answered INTERNAL too: a robot must never be handed them as a normal reply."""
    r = res.request
    if res.error is None:
        try:
            if res.actions is None:
                raise ValueError("a result with neither actions nor an error")
            if not np.isfinite(res.actions).all():
                log.error("request %r of %s: the model produced NaN or infinite actions; answering INTERNAL",
                          r.id, r.model)
                res.error = (ErrorCode.INTERNAL, "the model produced non-finite actions")
                return error_frames(r.id, *res.error)
            timings = Timings(queue_ms=max(0.0, res.admitted - r.arrival) * 1e3, vlm_ms=res.vlm_s * 1e3,
                              action_ms=res.action_s * 1e3, server_ms=(now - r.arrival) * 1e3)
            return encode(InferReply(id=r.id, model=r.model, actions=res.actions, timings=timings))
        except Exception:
            log.exception("could not make the reply to request %r; answering INTERNAL", r.id)
            res.error = (ErrorCode.INTERNAL, "the executor produced no valid reply")
    code, message = res.error
    return error_frames(r.id, code, message)


class ExecutorIO:
    # withdraw(): wait for the drain's answer (beyond the plane's traffic solve), for the router to fetch the
    # new table, for the requests accepted to be answered (all bounded: docker-compose gives executors 40 s
    # after SIGTERM, stop_grace_period), and how long no request may arrive before the engine is stopped.
    WITHDRAW_REPLY_S = 1.0
    WITHDRAW_SOLVE_S = 20.0
    WITHDRAW_ACK_S = 3.0
    WITHDRAW_ANSWER_S = 5.0
    WITHDRAW_QUIET_S = 0.25
    # Requests the engine failed in a row (INTERNAL from a failed batch, none answered with actions between them)
    # after which the device is taken to be in a sticky fault (on a GPU, e.g. an illegal memory access fails
    # every later launch): the executor leaves routing and exits 1 for its supervisor to restart it, instead of
    # heartbeating as healthy while it answers its whole share of the fleet INTERNAL.
    FAILED_IN_ROW_FATAL = 32
    FAILED_BATCHES_IN_ROW_FATAL = 4  # and in this many deliveries of results: one fault fails at most two at once

    def __init__(self, name: str, cfg: ClusterConfig, device: str, store: ModelStore, slot: EngineSlot,
                 hosted: Hosted, metrics: ExecutorMetrics | None = None, context: zmq.Context | None = None,
                 limits: dict[str, int] | None = None):
        self.name = name
        self.cfg = cfg
        self.device = device
        self.store = store
        self.slot = slot
        self.served: dict[str, ServedInput] = hosted.inputs  # replaced whole on a reload, never mutated
        self.limits = limits or {}  # measured robot limits of the models this executor owns
        # Names this process: a registration with another token is a restarted executor (a rollout
        # step waiting on this executor's reload must then send the load again).
        self.instance = uuid.uuid4().hex
        self.in_flight = 0  # requests handed to the engine and not yet answered (I/O thread only)
        self._reload: threading.Thread | None = None
        # A load that came while a reload ran (its rollout step timed out, and a later apply sent another): run after it.
        # Ignored, the executor kept the older load's models for good, as the plane reconciles a process only once.
        self._next_load: dict | None = None
        # The outcome of the last `load`, {id, ok, error?}: every registration carries it, so the control plane
        # reads from the registration after a reload whether the new models were loaded.
        self._load_outcome: dict | None = None
        self._reregister = threading.Event()
        self.fatal = threading.Event()  # serving cannot go on (a reload and its fallback failed, a sticky fault)
        self.fatal_reason = ""
        self._connection = 0  # connections to the router made so far (the hello's connection number)
        self._backend_up = False  # whether the connection to the router is up (its monitor's events)
        self._failed_in_row = 0  # requests the engine failed since it last answered one with actions
        self._failed_batches_in_row = 0  # deliveries of results holding those failures
        self._poller: zmq.Poller | None = None
        self._last_beat = 0.0
        self._leaving = False  # withdraw() has begun: no re-registration, no reloads
        self._ctl_replies: list[dict] = []  # control-plane answers withdraw() waits for
        self._last_request = 0.0  # monotonic time of the last request taken from the router
        self._telemetry = None
        self._last_lockstep = -1
        self._sm_count = 0
        if device.startswith("cuda"):
            import torch

            self._sm_count = torch.cuda.get_device_properties(torch.device(device)).multi_processor_count
        self.ctx = context or zmq.Context.instance()
        self.results: queue.SimpleQueue[list[Result]] = queue.SimpleQueue()
        self._unsent: deque[list] = deque()  # replies waiting for room in the router's pipe (MAX_UNSENT_REPLIES)
        self.dropped_replies = 0
        self.stats = {"requests": 0, "replies": 0, "errors": 0}
        self.metrics = metrics or ExecutorMetrics(name, device, {n: s.slo_s for n, s in self.served.items()})

        self.backend = self.ctx.socket(zmq.DEALER)
        self.backend.setsockopt(zmq.IDENTITY, name.encode())
        self.backend.setsockopt(zmq.LINGER, 1000)
        self.backend.setsockopt(zmq.MAXMSGSIZE, 2 * cfg.router.max_message_bytes + 65536)
        # A router whose host died is redialled once it is back (shared.service).
        keep_alive(self.backend, cfg.router.keepalive_s)
        # Each (re)connect to the router is reported here, so a restarted router hears our hello (and
        # instance) at once: otherwise it would learn our instance only at our next registration, and
        # could not tell a later restart of ours from our first hello (requests in flight to the old
        # process would then wait out router.request_timeout_s).
        self.backend_events = self.backend.get_monitor_socket(zmq.EVENT_CONNECTED | zmq.EVENT_DISCONNECTED)
        connect(self.backend, dial_address(cfg.router.backend, cfg.router.backend_connect))
        # Hello at once: with ROUTER_HANDOVER the connect takes this name over at the router, so it must learn
        # now, not after the engine has started (seconds to minutes), that an earlier process of this name is
        # gone and its requests in flight will never be answered. Requests routed here meanwhile wait in this
        # socket for run(); a later hello (each registration) repeats the same instance, which changes nothing.
        self._hello()

        self.ctl = self.ctx.socket(zmq.DEALER)
        self.ctl.setsockopt(zmq.IDENTITY, name.encode())  # the control plane addresses load requests by name
        self.ctl.setsockopt(zmq.LINGER, 0)
        # A connection whose name another peer took (ROUTER_HANDOVER at the plane detaches it without closing it) is
        # found and redialled: until then every heartbeat went into it, and the plane dropped us.
        keep_alive(self.ctl, cfg.router.keepalive_s)
        # Whether the control plane's connection is up (_ctl_connected): a message to a plane that is down is
        # queued, not refused, so only this tells withdraw() not to wait for a drain's answer that cannot come.
        self.ctl_events = self.ctl.get_monitor_socket(zmq.EVENT_CONNECTED | zmq.EVENT_DISCONNECTED)
        self._ctl_up = False
        connect(self.ctl, dial_address(cfg.control.bind, cfg.control.connect))

        addr = f"inproc://executor-wake-{id(self)}"
        self.wake_rx = self.ctx.socket(zmq.PAIR)
        self.wake_rx.bind(addr)
        self.wake_tx = self.ctx.socket(zmq.PAIR)
        self.wake_tx.connect(addr)
        self._wake_lock = threading.Lock()

    def on_results(self, results: list[Result]) -> None:
        """Called on the engine thread: hand results over and wake the I/O thread."""
        self.results.put(results)
        with self._wake_lock:
            try:
                self.wake_tx.send(b"", zmq.NOBLOCK)
            except zmq.Again:  # the wake-up pipe is full: the I/O thread has wake-ups pending anyway
                pass

    def _ctl_send(self, kind: str, **fields) -> bool:
        """Send to the control plane without ever blocking the I/O thread; False when dropped.

        While the control plane is unreachable ZeroMQ queues 1000 messages for it and a
        blocking send then waits for it to come back: the robots' requests would go
        unanswered meanwhile, and SIGTERM would hang in ``withdraw``/``close``. Dropping is
        safe: heartbeats repeat, a control plane that hears a heartbeat from an executor it
        does not know asks it to ``reregister``, and ``withdraw``'s waits are bounded.
        """
        try:
            self.ctl.send(control.pack(kind, **fields), zmq.NOBLOCK)
            return True
        except zmq.Again:
            log.debug("control plane unreachable: %s not sent", kind)
            return False

    def _ctl_connected(self) -> bool:
        """Whether the connection to the control plane is up, from the events its monitor holds."""
        self._ctl_up = connection_up(self.ctl_events, self._ctl_up)
        return self._ctl_up

    def register(self) -> None:
        self._ctl_send("register", executor=self.name, device=self.device, instance=self.instance,
                       models={n: s.info.to_wire() for n, s in self.served.items()}, limits=self.limits,
                       load=self._load_outcome, settings={n: settings_digest(s.config) for n, s in self.served.items()})
        self._hello()

    def _hello(self) -> None:
        """Say hello to the router so its ROUTER socket knows our identity before the first request; the
        instance tells it a restarted process from this one, so it fails what the old one never answers."""
        # The connection number tells the router a reconnect from the same process (RECONNECT_ANSWER_S there);
        # none before the first connect is reported, whose hello repeats this one.
        fields = {"connection": self._connection} if self._connection else {}
        try:
            self.backend.send_multipart([b"", control.pack("executor_hello", executor=self.name,
                                                           instance=self.instance, **fields)], zmq.NOBLOCK)
        except zmq.Again:  # the pipe to the router is full: requests are flowing, and the next registration repeats it
            log.debug("router pipe full: hello not sent")

    def answer_while_starting(self, started: threading.Event, stop: threading.Event) -> None:
        """Until ``started`` (or ``stop``), before this process registers: answer every request UNAVAILABLE at once.

        The router routes here by the registry entry of an earlier process of this name until that entry times
        out, and the engine's start (graph capture, profiling) takes seconds to minutes. Left in the socket, those
        requests were served after the start as if they had just come (a deadline counts from when a request is
        read), with actions for observations minutes old. The engine is not there yet, so each is refused.
        """
        poller = zmq.Poller()
        for s in (self.backend, self.backend_events):
            poller.register(s, zmq.POLLIN)
        while not started.is_set() and not stop.is_set():
            ready = dict(poller.poll(50))
            self._take_requests(ready)
            self._flush_unsent()

    def _take_requests(self, ready: dict) -> None:
        """Say hello again after a reconnect, and take up to 256 requests from the router (``ready``: a poll's)."""
        if self.backend_events in ready:
            for event in monitor_events(self.backend_events):
                if event == zmq.EVENT_DISCONNECTED:
                    self._backend_up = False
                elif event == zmq.EVENT_CONNECTED:
                    self._backend_up = True
                    self._connection += 1
                    self._hello()  # the same instance again to a router that knows it changes nothing
        if self.backend in ready:
            for _ in range(256):
                try:
                    frames = self.backend.recv_multipart(zmq.NOBLOCK, copy=False)
                except zmq.Again:
                    break
                self._on_request(frames)

    def run(self, stop: threading.Event) -> None:
        """Serve until ``stop``; the caller then calls ``withdraw`` before stopping the engine."""
        self._poller = zmq.Poller()
        for s in (self.backend, self.ctl, self.wake_rx, self.backend_events):
            self._poller.register(s, zmq.POLLIN)
        self.register()
        self._last_beat = time.monotonic()
        while not stop.is_set() and not self.fatal.is_set():
            self._serve_once()

    def _serve_once(self, timeout_ms: int = 50) -> None:
        """One turn of the I/O loop: results out, requests in, control messages, heartbeat."""
        ready = dict(self._poller.poll(timeout_ms))
        if self.wake_rx in ready:
            while True:
                try:
                    self.wake_rx.recv(zmq.NOBLOCK)
                except zmq.Again:
                    break
        self._send_results()
        if self._unsent:
            self._poller.modify(self.backend, zmq.POLLIN | zmq.POLLOUT)  # woken as the pipe frees up
        else:
            self._poller.modify(self.backend, zmq.POLLIN)
        self._take_requests(ready)
        if self.ctl in ready:
            while True:
                try:
                    msg = control.unpack(self.ctl.recv(zmq.NOBLOCK))
                except zmq.Again:
                    break
                except ProtocolError:
                    continue
                kind = msg.get("kind")
                if self._leaving:
                    # Answers to withdraw()'s requests; a control plane that lost us must not
                    # route to us again (reregister) nor move models here (load) while we leave.
                    if kind in ("ok", "error", "status"):
                        self._ctl_replies.append(msg)
                elif kind == "reregister":
                    self.register()
                elif kind == "load":
                    self._start_reload(msg)
                elif kind == "error":
                    # The control plane refused something we sent (e.g. a registration it cannot
                    # read, which would leave us off the routing table): say so where operators look.
                    log.error("the control plane refused our message: %s (%s)", msg.get("message"), msg.get("code"))
        if self._reregister.is_set() and not self._leaving:
            self._reregister.clear()
            # The metrics judge replies by the new model set's deadlines before the registration lets traffic in,
            # not from the next heartbeat on: a reply in between was judged by the old deadline, or by none.
            self.metrics.serve_models({n: s.slo_s for n, s in self.served.items()})
            self.register()
        if (self._next_load is not None and not self._leaving and not self._reload.is_alive()
                and not self._reregister.is_set()):  # the finished reload's outcome is registered first
            msg, self._next_load = self._next_load, None
            self._start_reload(msg)
        now = time.monotonic()
        if now - self._last_beat >= self.cfg.control.heartbeat_s:
            self._last_beat = now
            # Reads the monitor's events as they come, so they never pile up. A heartbeat to a plane that is down is
            # skipped: queued, the outage's whole backlog would reach a restarted plane at once, and it asks an
            # executor it does not know to re-register once per heartbeat.
            plane_up = self._ctl_connected()
            if self.slot.failed() and not self.fatal.is_set():
                # Registered and heartbeating, it would refuse its whole share of the fleet: leave for a restart.
                log.critical("the engine's loop ended on a fault; leaving routing and exiting for a restart")
                self.fatal_reason = "the engine's loop ended on a fault"
                self.fatal.set()
            depths = self.slot.depths()
            if plane_up:
                self._ctl_send("heartbeat", executor=self.name, depths=depths)
            # A message to the router every heartbeat too. A connection the router detached without closing it
            # (another peer took this name: ROUTER_HANDOVER) still answers ZMTP pings until a message is stuck in it;
            # only then does keep_alive's timeout find it. An idle executor sent nothing, and was never reached again.
            # None while disconnected: queued, they would reach a restarted router ahead of the reconnect's hello,
            # under the old connection's number, and make the reconnect look like one from a connection it knew.
            if self._backend_up:
                self._hello()
            self._update_gauges(depths)

    def _ctl_reply(self, kinds: tuple[str, ...], timeout_s: float) -> dict | None:
        """Serve (requests and results keep flowing) until a control-plane reply of ``kinds`` arrives."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            for i, msg in enumerate(self._ctl_replies):
                if msg.get("kind") in kinds:
                    del self._ctl_replies[: i + 1]
                    return msg
            self._serve_once(20)
        return None

    def withdraw(self, ack_timeout_s: float | None = None, answer_timeout_s: float | None = None) -> None:
        """On shutdown, before the engine stops: leave routing without failing a request.

        1. Drain ourselves on the control plane (as `robion ctl drain` does): the new table
           routes nothing new here but still lists us, so the router passes our replies on.
        2. Keep serving until the router has fetched that table (the control plane reports
           the version the router polls with), so requests it sent before are all accepted.
        3. Keep serving until every accepted request is answered and nothing new came for
           ``WITHDRAW_QUIET_S`` (a request forwarded just before the switch may still be in
           transit).
        Every wait is bounded (the control plane or router may already be gone); whatever the
        engine still holds afterwards is answered by its ``finish``, and ``close`` deregisters.
        """
        ack_timeout_s = self.WITHDRAW_ACK_S if ack_timeout_s is None else ack_timeout_s
        answer_timeout_s = self.WITHDRAW_ANSWER_S if answer_timeout_s is None else answer_timeout_s
        if self._poller is None:  # never served: nothing can be in flight
            return
        t0 = time.monotonic()
        self._leaving = True
        self._ctl_replies.clear()
        sent = self._ctl_send("drain", executor=self.name)
        # The control plane re-solves the traffic plan before it answers a drain, for up to its solve time limit
        # (at most WITHDRAW_SOLVE_S of it: a container's stop grace is 40 s); a drain that could not even be queued,
        # or went to a plane that is not connected, is not waited for beyond WITHDRAW_REPLY_S.
        answerable = sent and self._ctl_connected()
        solve_s = min(self.cfg.control.solve_time_limit_s, self.WITHDRAW_SOLVE_S) if answerable else 0.0
        reply = self._ctl_reply(("ok", "error"), solve_s + min(self.WITHDRAW_REPLY_S, ack_timeout_s))
        if reply is None:
            log.warning("control plane did not answer our drain: leaving without waiting for the router")
        elif reply.get("kind") == "error":
            log.info("control plane does not list us (%s): no routes to withdraw", reply.get("message"))
        else:
            version = int(reply.get("version", 0))
            end = time.monotonic() + ack_timeout_s  # from the answer, which may come after a long solve
            acked = False
            while not acked and time.monotonic() < end:
                self._ctl_send("status")
                status = self._ctl_reply(("status",), min(0.5, max(0.0, end - time.monotonic())))
                router = (status or {}).get("status", {}).get("router", {})
                acked = int(router.get("version", -1)) >= version
                if not acked:
                    self._serve_once(50)
            if acked:
                log.info("withdrawn from routing (table v%d) in %.2f s", version, time.monotonic() - t0)
            else:
                log.warning("router did not pick up table v%d within %.1f s; stopping anyway", version, ack_timeout_s)
        end = time.monotonic() + answer_timeout_s
        while time.monotonic() < end:
            if self.in_flight <= 0 and time.monotonic() - self._last_request >= self.WITHDRAW_QUIET_S:
                break
            self._serve_once(20)
        if self.in_flight > 0:
            log.warning("%d requests still in flight after %.1f s; the engine answers them as it stops",
                        self.in_flight, answer_timeout_s)

    def _start_reload(self, msg: dict) -> None:
        if self._reload is not None and self._reload.is_alive():
            log.warning("a model reload is already running; the load that came meanwhile runs after it")
            self._next_load = msg  # the newest: it is the control plane's latest word
            return
        load_id = msg.get("load_id")
        try:
            configs = [ModelConfig(**m) for m in msg["models"]]
        except (KeyError, TypeError) as exc:
            log.error("malformed load request: %s", exc)
            if isinstance(load_id, str):  # answered, so the rollout moves on instead of waiting out its step
                self._load_outcome = {"id": load_id, "ok": False, "error": f"malformed load request: {exc}"}
                self.register()
            return
        self._reload = threading.Thread(target=self._reload_models, args=(configs, load_id), name="reload",
                                        daemon=True)
        self._reload.start()

    def _reload_models(self, configs: list[ModelConfig], load_id: str | None = None) -> None:
        """Off the I/O thread: wait for held requests to be answered, then swap models and engine."""
        outcome: dict = {"id": load_id, "ok": True}
        names = [mc.name for mc in configs]
        previous = [s.config for s in self.served.values()]
        log.info("reloading with models %s: waiting for %d requests in flight", names, self.in_flight)
        end = time.monotonic() + 60
        while self.in_flight > 0 and time.monotonic() < end:
            time.sleep(0.01)
        self.slot.stop()  # anything still held is answered UNAVAILABLE by the engine's finish
        # The I/O thread's view (self.served) changes while no engine runs, so a request in
        # between meets no engine (UNAVAILABLE) rather than a new engine without its model.
        failure = None
        try:
            hosted = self.store.load(configs)
            self.served = hosted.inputs
            took = self.slot.start(hosted)
        except Exception as exc:
            # The traceback as text: a log record holding the exception (a handler that keeps records) would keep
            # its frames, and with them what the failed attempt allocated.
            log.error("loading %s failed; keeping the previous models\n%s", names, traceback.format_exc())
            failure = f"{type(exc).__name__}: {exc}"[:500]
        if failure is not None:
            # Out of the except block: its traceback held the failed engine (buffers, graph pools) and the new
            # models' weights through the fallback, which on a device that ran out of memory could then run out too.
            outcome = {"id": load_id, "ok": False, "error": failure}
            hosted = None
            self.served = {}
            free_memory()
            try:
                hosted = self.store.load(previous)
                self.served = hosted.inputs
                took = self.slot.start(hosted)
            except Exception:
                # No engine and no way back (weights gone, device memory taken): an executor
                # that stayed up would answer every request UNAVAILABLE and never register
                # again. Leave instead, so routing drops it and a supervisor restarts it.
                log.critical("loading the previous models %s failed too; leaving", [mc.name for mc in previous],
                             exc_info=True)
                self.fatal_reason = "no models could be loaded after a failed reload"
                self.fatal.set()  # the I/O loop ends within one poll; main then withdraws and exits 1
                return
        if self.cfg.control.limits.auto:
            # A limit holds for the settings it was measured at (rate, deadline): the start-up ones no longer
            # describe models whose settings the reload changed, nor those it added or removed. Cached ones
            # only: a capacity search here would keep this executor out of routing for minutes.
            self.limits = measure_limits(self.cfg, self.name, hosted.models, self.store.device, measure=False,
                                         settings={n: s.config for n, s in hosted.inputs.items()})
        log.info("now serving %s (engine ready in %.1f s)", sorted(hosted.inputs), took)
        self._load_outcome = outcome
        self._reregister.set()

    def drain(self, timeout_s: float = 5.0) -> None:
        """After the engine stopped: send every remaining result so no request goes unanswered (within
        ``timeout_s``: a router that is gone takes none of them, and a stop must not wait for it)."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if not self._send_results() and not self._unsent:
                break
            if self._unsent:
                time.sleep(0.01)
        if self._unsent:
            log.warning("%d replies could not be sent (the router is not taking them)", len(self._unsent))

    def _send_reply(self, frames: list) -> None:
        """Hand a reply to the router's pipe without blocking. A blocking send to a router that is gone
        (ZeroMQ queues for it up to the high-water mark, then waits) held the I/O thread for good: no
        heartbeats, no control messages, and a stop was never seen."""
        if not self._unsent:
            try:
                self.backend.send_multipart(frames, flags=zmq.NOBLOCK, copy=False)
                return
            except zmq.Again:
                log.warning("the router is not taking replies (its pipe is full): holding them")
        self._unsent.append(frames)
        if len(self._unsent) > MAX_UNSENT_REPLIES:
            self._unsent.popleft()
            self.dropped_replies += 1
            if self.dropped_replies % 1000 == 1:
                log.warning("dropped %d replies the router did not take (oldest first)", self.dropped_replies)

    def _flush_unsent(self) -> None:
        while self._unsent:
            try:
                self.backend.send_multipart(self._unsent[0], flags=zmq.NOBLOCK, copy=False)
            except zmq.Again:
                return
            self._unsent.popleft()

    def close(self) -> None:
        # Leave the routing table now rather than after missed heartbeats.
        self._ctl_send("deregister", executor=self.name)
        self.ctl.setsockopt(zmq.LINGER, 500)
        self.backend.disable_monitor()
        self.ctl.disable_monitor()
        for s in (self.backend_events, self.ctl_events, self.backend, self.ctl, self.wake_rx, self.wake_tx):
            s.close()

    def _update_gauges(self, depths: dict[str, int]) -> None:
        # On this thread, which alone records results: a reload's new model set (and deadlines) takes effect in the
        # metrics here; the series of a model it took away would show their last values forever.
        served = self.served
        if self._reload is None or not self._reload.is_alive():
            # Not mid-reload: a failed one empties self.served while it loads the previous models back, and served
            # models then were dropped and came back with a fresh attainment window, their settings unchanged. The
            # reload's outcome takes effect at its re-registration (_reregister, above).
            self.metrics.serve_models({n: s.slo_s for n, s in served.items()})
        # A model with no engine queue (its engine is being replaced) holds nothing: whatever
        # it held was answered when the old engine stopped.
        for model in served:
            self.metrics.queue_depth.labels(model).set(depths.get(model, 0))
        self._observe_locksteps()
        if self.device.startswith("cuda"):
            import torch

            self.metrics.gpu_memory.labels(self.device).set(torch.cuda.memory_reserved(torch.device(self.device)))

    def _observe_locksteps(self) -> None:
        """Feed the lockstep engine's telemetry records that arrived since the last call into the metrics."""
        telemetry = getattr(self.slot.engine, "telemetry", None)
        if telemetry is None:
            return
        if telemetry is not self._telemetry:  # a reload brought a new engine: its indices restart
            self._telemetry, self._last_lockstep = telemetry, -1
        for rec in telemetry.records():
            if rec.index <= self._last_lockstep:
                continue
            self._last_lockstep = rec.index
            # Only lockstep records have a duration: procdisagg keeps per-step and interdisagg per-batch
            # records, which are no locksteps (and reading a field they lack would end the I/O loop).
            duration_ms = getattr(rec, "duration_ms", None)
            if duration_ms is not None:
                self.metrics.lockstep.observe(duration_ms / 1e3)
            gap = getattr(rec, "cpu_gap_us", None)
            if gap is not None:
                self.metrics.lockstep_gap.observe(gap / 1e6)
            if rec.vlm_batch:
                # A CPU has no SMs: NaN there ("no value"), not 0, which read as a VLM restricted to nothing.
                self.metrics.sm_level.set(rec.sm_level if rec.sm_level is not None else self._sm_count or math.nan)

    def _count_failures(self, results: list[Result]) -> None:
        """Track the engine's failed requests in a row (before reply_frames, whose own INTERNAL answers, such as
        non-finite actions a robot's input can cause, are no device fault); past FAILED_IN_ROW_FATAL requests over
        at least FAILED_BATCHES_IN_ROW_FATAL deliveries with no answer between them, leave. One transient fault
        fails a lockstep's two batches in one delivery, which at a large max_batch alone held 32 requests."""
        if any(res.error is None for res in results):
            self._failed_in_row = self._failed_batches_in_row = 0
            return
        failed = sum(res.error[0] == ErrorCode.INTERNAL for res in results if res.error is not None)
        if not failed:
            return
        self._failed_in_row += failed
        self._failed_batches_in_row += 1
        faulted = (self._failed_in_row >= self.FAILED_IN_ROW_FATAL
                   and self._failed_batches_in_row >= self.FAILED_BATCHES_IN_ROW_FATAL)
        if faulted and not self.fatal.is_set():
            log.critical("the engine failed %d requests in %d batches in a row and answered none: the device looks "
                         "faulted; leaving routing and exiting for a restart", self._failed_in_row,
                         self._failed_batches_in_row)
            self.fatal_reason = (f"the engine failed {self._failed_in_row} requests in {self._failed_batches_in_row} "
                                 "batches in a row")
            self.fatal.set()

    def _send_results(self) -> bool:
        self._flush_unsent()
        sent = False
        while True:
            try:
                batch = self.results.get_nowait()
            except queue.Empty:
                return sent
            now = time.monotonic()
            batches: dict[tuple[str, float], int] = {}
            self._count_failures(batch)
            for res in batch:
                r = res.request
                self._send_reply([r.envelope, *reply_frames(res, now)])
                self.in_flight -= 1
                sent = True
                if res.error is not None:
                    self.stats["errors"] += 1
                    self.metrics.observe_result(r.model, res.error[0].value.lower(), now - r.arrival, 0, 0, 0)
                    continue
                self.stats["replies"] += 1
                self.metrics.observe_result(r.model, "ok", now - r.arrival, res.admitted - r.arrival, res.vlm_s,
                                            res.action_s)
                key = (r.model, res.admitted)  # members of one batch share their admission time
                batches[key] = batches.get(key, 0) + 1
            for (model, _), size in batches.items():
                self.metrics.observe_batch(model, size)

    def _on_request(self, frames: list[zmq.Frame]) -> None:
        if len(frames) < 2:
            return  # the router's probe of our connection (one empty frame): not a request
        arrival = self._last_request = time.monotonic()
        envelope = frames[0].bytes
        body = [f.buffer for f in frames[1:]]
        rid = ""
        header: dict = {}
        try:
            header = unpack_header(body[0])
            rid = header_id(header)
            if message_bytes(body) > self.cfg.router.max_message_bytes:
                raise ProtocolError(ErrorCode.TOO_LARGE, f"message beyond {self.cfg.router.max_message_bytes} bytes")
            msg = decode(body, header)
            if not isinstance(msg, InferRequest):
                raise ProtocolError(ErrorCode.BAD_REQUEST, "executors take only infer requests")
            served = self.served.get(msg.model)
            if served is None:
                # Requests come only through the router, which forwards only models of its routing table: this
                # one was routed by a table older than our model set (a placement change in progress, a restart
                # with other models, one an `apply` added that our config file does not name). Another executor
                # serves it, so retry; the router itself answers UNKNOWN_MODEL for names the cluster lacks.
                raise ProtocolError(ErrorCode.UNAVAILABLE, f"model {msg.model!r} is not served by {self.name} now")
            self.slot.submit(to_request(msg, served, envelope, arrival))
            self.stats["requests"] += 1
            self.in_flight += 1
        except ProtocolError as exc:
            self._refuse(envelope, rid, header, exc.code, exc.message, arrival)
        except Exception as exc:  # never let one request take the executor down
            log.exception("failed to accept request %r", rid)
            self._refuse(envelope, rid, header, ErrorCode.INTERNAL, type(exc).__name__, arrival)

    def _refuse(self, envelope: bytes, rid: RequestId, header: dict, code: ErrorCode, message: str, arrival: float) -> None:
        """Answer a request that never reached the engine, and count it like the engine's errors.

        A refusal (queue full, bad shape, a fault) is an answer with an error: for a served
        model it is one more request past its SLO, or the attainment would read 1.0 on an
        executor refusing most of its traffic. Other names share the "" label, so clients
        cannot grow the number of series.
        """
        self.stats["errors"] += 1
        self._send_reply([envelope, *error_frames(rid, code, message)])
        model = header.get("model")
        if isinstance(model, str) and model in self.served:
            self.metrics.observe_result(model, code.value.lower(), time.monotonic() - arrival, 0, 0, 0)
        else:
            self.metrics.requests.labels("", code.value.lower()).inc()
