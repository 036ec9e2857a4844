"""The router's socket loop: robots on one ROUTER socket, executors on another.

Only the small msgpack header of a request is decoded; image frames are forwarded to the
executor untouched. Every request gets exactly one answer: the executor's reply, or an
error from here when the request is malformed, unroutable, or its executor went away.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import zmq

from services.router.routing import Routing
from shared import control
from shared.config import ClusterConfig, dial_address
from shared.control import RoutingTable
from shared.metrics import RouterMetrics, serve
from shared.protocol import (ErrorCode, Metadata, Pong, ProtocolError, encode, error_frames, header_id,
                             message_bytes, unpack_header)

log = logging.getLogger("robion.router")

MAX_IN_FLIGHT = 65536
TABLE_POLL_S = 0.1


@dataclass
class InFlight:
    executor: str
    model: str
    sent_at: float


class Router:
    def __init__(self, cfg: ClusterConfig, context: zmq.Context | None = None):
        self.cfg = cfg
        self.ctx = context or zmq.Context.instance()
        self.routing = Routing()
        self.in_flight: dict[tuple[bytes, str], InFlight] = {}
        self.stats = {"requests": 0, "replies": 0, "errors": 0}
        self.metrics = RouterMetrics()
        serve(self.metrics.registry, cfg.router.metrics_port)
        limit = cfg.router.max_message_bytes

        self.frontend = self.ctx.socket(zmq.ROUTER)
        # Frames far beyond the limit are refused by libzmq itself (the peer is disconnected)
        # so a hostile sender cannot make the router buffer gigabytes; anything up to twice
        # the limit is read and answered with TOO_LARGE.
        self.frontend.setsockopt(zmq.MAXMSGSIZE, 2 * limit + 65536)
        self.frontend.setsockopt(zmq.LINGER, 0)
        self.frontend.setsockopt(zmq.ROUTER_HANDOVER, 1)  # a reconnecting robot keeps its identity
        self.frontend.bind(cfg.router.bind)

        self.backend = self.ctx.socket(zmq.ROUTER)
        self.backend.setsockopt(zmq.ROUTER_MANDATORY, 1)  # unreachable executor -> error, not a silent drop
        self.backend.setsockopt(zmq.ROUTER_HANDOVER, 1)
        self.backend.setsockopt(zmq.LINGER, 0)
        self.backend.bind(cfg.router.backend)

        self.ctl = self.ctx.socket(zmq.DEALER)
        self.ctl.setsockopt(zmq.LINGER, 0)
        self.ctl.connect(dial_address(cfg.control.bind, cfg.control.connect))
        self._last_table_poll = 0.0
        self._last_sweep = 0.0

    # ------------------------------------------------------------------ loop

    def run(self, stop: threading.Event) -> None:
        poller = zmq.Poller()
        for s in (self.frontend, self.backend, self.ctl):
            poller.register(s, zmq.POLLIN)
        while not stop.is_set():
            now = time.monotonic()
            if now - self._last_table_poll >= TABLE_POLL_S:
                self._last_table_poll = now
                self.ctl.send(control.pack("table_get", version=self.routing.table.version, role="router"))
            if now - self._last_sweep >= 0.1:
                self._last_sweep = now
                self._expire(now)
            for sock, _ in poller.poll(50):
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
        self.close()

    def close(self) -> None:
        for s in (self.frontend, self.backend, self.ctl):
            s.close(linger=0)

    # ------------------------------------------------------------------ robots

    def _reply_error(self, robot: bytes, rid: str, code: ErrorCode, message: str, model: str = "") -> None:
        self.stats["errors"] += 1
        # Only served model names become label values: robots cannot grow the series count.
        self.metrics.requests.labels(model if self.routing.knows(model) else "", code.value.lower()).inc()
        self.frontend.send_multipart([robot, *error_frames(rid, code, message)], copy=False)

    def _from_robot(self, frames: list[zmq.Frame]) -> None:
        robot = frames[0].bytes
        body = frames[1:]
        if not body:
            return self._reply_error(robot, "", ErrorCode.BAD_REQUEST, "empty message")
        size = message_bytes([f.buffer for f in body])
        try:
            header = unpack_header(body[0].buffer)
        except ProtocolError as exc:
            return self._reply_error(robot, "", exc.code, exc.message)
        rid = header_id(header)
        if size > self.cfg.router.max_message_bytes:
            return self._reply_error(robot, rid, ErrorCode.TOO_LARGE,
                                     f"message is {size} bytes; the limit is {self.cfg.router.max_message_bytes}")
        kind = header.get("kind")
        if kind == "hello":
            table = self.routing.table
            self.frontend.send_multipart([robot, *encode(Metadata(id=rid, models=table.models))], copy=False)
            return
        if kind == "ping":
            self.frontend.send_multipart([robot, *encode(Pong(id=rid))], copy=False)
            return
        if kind != "infer":
            return self._reply_error(robot, rid, ErrorCode.BAD_REQUEST, f"kind: unknown message kind {kind!r}")
        model = header.get("model")
        if not isinstance(model, str):
            return self._reply_error(robot, rid, ErrorCode.BAD_REQUEST, "model: expected str")
        if not rid:
            return self._reply_error(robot, rid, ErrorCode.BAD_REQUEST, "id: expected a non-empty str or int")
        if not self.routing.knows(model):
            return self._reply_error(robot, rid, ErrorCode.UNKNOWN_MODEL, f"model {model!r} is not served")
        key = (robot, rid)
        if key in self.in_flight:
            return self._reply_error(robot, rid, ErrorCode.BAD_REQUEST, f"id: request {rid!r} is already in flight")
        if len(self.in_flight) >= MAX_IN_FLIGHT:
            return self._reply_error(robot, rid, ErrorCode.OVERLOADED, "too many requests in flight")
        self.stats["requests"] += 1
        for executor in self.routing.candidates(model, robot):
            try:
                self.backend.send_multipart([executor.encode(), robot, *body], copy=False)
            except zmq.ZMQError as exc:
                if exc.errno == zmq.EHOSTUNREACH:  # registered but not connected to us (yet / any more)
                    continue
                raise
            self.in_flight[key] = InFlight(executor, model, time.monotonic())
            self.metrics.in_flight.set(len(self.in_flight))
            return
        self._reply_error(robot, rid, ErrorCode.UNAVAILABLE, f"no executor for {model!r} is reachable", model)

    # ------------------------------------------------------------------ executors

    def _from_executor(self, frames: list[zmq.Frame]) -> None:
        if len(frames) < 3:
            return
        robot = frames[1].bytes
        body = frames[2:]
        if not robot:  # an executor's own message (hello on connect); nothing to forward
            return
        try:
            header = unpack_header(body[0].buffer)
        except ProtocolError:
            log.warning("executor %s sent an undecodable reply header", frames[0].bytes)
            return
        rid = header_id(header)
        flight = self.in_flight.pop((robot, rid), None)
        if flight is None:
            return  # already answered (timed out or executor declared gone): one answer per request
        self.stats["replies"] += 1
        status = "ok" if header.get("kind") == "reply" else str(header.get("code", "internal")).lower()
        self.metrics.requests.labels(flight.model, status).inc()
        self.metrics.in_flight.set(len(self.in_flight))
        if status == "ok":
            self.metrics.latency.labels(flight.model).observe(time.monotonic() - flight.sent_at)
        self.frontend.send_multipart([robot, *body], copy=False)

    def _expire(self, now: float) -> None:
        timeout = self.cfg.router.request_timeout_s
        stale = [k for k, f in self.in_flight.items() if now - f.sent_at > timeout]
        for robot, rid in stale:
            f = self.in_flight.pop((robot, rid))
            self._reply_error(robot, rid, ErrorCode.UNAVAILABLE, f"executor {f.executor} did not answer within {timeout} s",
                              f.model)

    def _fail_executor(self, executor: str) -> None:
        lost = [k for k, f in self.in_flight.items() if f.executor == executor]
        for robot, rid in lost:
            f = self.in_flight.pop((robot, rid))
            self._reply_error(robot, rid, ErrorCode.UNAVAILABLE, f"executor {executor} went away", f.model)
        if lost:
            log.warning("executor %s left the routing table with %d requests in flight", executor, len(lost))

    # ------------------------------------------------------------------ control plane

    def _from_control(self, frames: list[zmq.Frame]) -> None:
        msg = control.unpack(frames[-1].buffer)
        if msg.get("kind") == "table" and msg.get("table") is not None:
            table = RoutingTable.from_wire(msg["table"])
            if table.version != self.routing.table.version:
                gone = self.routing.update(table)
                self.metrics.table_version.set(table.version)
                self.metrics.executors.set(len({e for ex in table.routes.values() for e in ex}))
                log.info("routing table v%d: %s", table.version,
                         {m: e for m, e in table.routes.items()})
                for executor in gone:
                    self._fail_executor(executor)
