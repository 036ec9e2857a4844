"""The router against peers that misbehave: a stalled executor, many-frame messages, odd ids and
versions, and models with no executor right now.

Each test runs the real Router loop in a thread on loopback TCP sockets; the executor is a
DEALER the test drives (it never reads, or it answers with the real protocol encoder), and the
routing table is made by hand or by the control plane's own ClusterState.
"""

from __future__ import annotations

import threading
import time
from collections import Counter

import msgpack
import numpy as np
import pytest
import zmq

from services.controlplane.state import ClusterState
from services.router.frontend import Router
from shared import control
from shared.config import load_config
from shared.control import RoutingTable
from shared.protocol import (MAX_FRAMES, ErrorCode, ErrorReply, InferReply, InferRequest, Metadata, ModelInfo,
                             ProtocolError, decode, encode, error_frames, header_id, pack_header)
from tests.helpers import cluster_config

INFO = ModelInfo(cameras=["cam0", "cam1"], image_shape=[64, 64, 3], state_dim=8, horizon=10, action_dim=7,
                 deadline_ms=500.0, arch="toy")


def infer_frames(rid, model: str = "toy-a", **header) -> list[bytes]:
    """A valid infer request for INFO's shapes: header + two 12 KiB image frames (state inline)."""
    rng = np.random.default_rng(0)
    frames = [bytes(f) for f in encode(InferRequest(
        id="x", robot="r", model=model, instruction="pick",
        images={c: rng.integers(0, 256, INFO.image_shape, dtype=np.uint8) for c in INFO.cameras},
        state=np.zeros(INFO.state_dim, np.float32)))]
    h = msgpack.unpackb(frames[0])
    h.update(id=rid, **header)
    return [pack_header(h), *frames[1:]]


class RouterThread:
    """A real Router running its loop in a thread, with sockets the test uses to play robots and executors."""

    def __init__(self, tmp_path, table: RoutingTable | None = None, **router_cfg):
        path, _ = cluster_config(tmp_path)
        cfg = load_config(path)
        for k, v in router_cfg.items():
            setattr(cfg.router, k, v)
        self.cfg = cfg
        self.ctx = zmq.Context()
        self.router = Router(cfg, self.ctx)
        if table is not None:
            self.router.routing.update(table)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.router.run, args=(self.stop,), daemon=True)
        self.socks: list[zmq.Socket] = []
        self.peers: list[threading.Thread] = []  # answering executors, stopped before their sockets close
        self.peers_stop = threading.Event()

    def __enter__(self) -> "RouterThread":
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.peers_stop.set()
        for t in self.peers:
            t.join(5)
        # Peers go first, and the router's I/O thread is given time to see them go while its
        # sockets are still open. A router socket closing at the moment a peer drops a
        # connection it is half-way through sending a multipart request on trips an assertion
        # inside libzmq 4.3.5 (session_base.cpp, clean_pipes; zeromq/libzmq#3442).
        for s in self.socks:
            s.close(linger=0)
        time.sleep(0.3)
        self.stop.set()
        self.thread.join(5)
        assert not self.thread.is_alive(), "router loop did not stop"
        self.ctx.term()

    def robot(self, identity: bytes) -> zmq.Socket:
        s = self.ctx.socket(zmq.DEALER)
        s.setsockopt(zmq.IDENTITY, identity)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.SNDHWM, 0)  # the test's own sends never block or drop
        s.setsockopt(zmq.RCVHWM, 0)
        s.connect(self.cfg.router.bind)
        self.socks.append(s)
        return s

    def executor(self, name: bytes, rcvhwm: int = 1000) -> zmq.Socket:
        """A DEALER the router can route to; returns once the router has seen it connect."""
        s = self.ctx.socket(zmq.DEALER)
        s.setsockopt(zmq.IDENTITY, name)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.RCVHWM, rcvhwm)
        s.connect(self.cfg.router.backend)
        self.socks.append(s)
        s.send(b"")  # the router ignores a one-frame message; its handshake makes the identity routable
        time.sleep(0.2)
        return s


    def answering_executor(self, name: bytes, hold: int = 1) -> zmq.Socket:
        """An executor that answers with the real protocol code: decode each request, reply with its own id.

        Requests are held until ``hold`` have arrived, so that many are in flight at the router at once.
        Its receive queue is unbounded, so it never pushes back on the router however slowly it answers.
        """
        sock = self.executor(name, rcvhwm=0)

        def loop() -> None:
            pending = []
            while not self.peers_stop.is_set():
                if not sock.poll(50):
                    continue
                robot, *body = sock.recv_multipart()
                if not body:
                    continue  # the router's probe of the connection, after another executor's closed
                try:
                    req = decode(body)
                except ProtocolError as exc:  # as the executor does: an error reply with the request's id
                    sock.send_multipart([robot, *error_frames(header_id(msgpack.unpackb(body[0])), exc.code,
                                                              exc.message)])
                    continue
                pending.append((robot, req))
                if len(pending) >= hold:
                    for robot, req in reversed(pending):
                        actions = np.zeros((INFO.horizon, INFO.action_dim), np.float32)
                        sock.send_multipart([robot, *encode(InferReply(id=req.id, model=req.model, actions=actions))])
                    pending = []

        t = threading.Thread(target=loop, daemon=True)
        t.start()
        self.peers.append(t)
        return sock

def ask(sock: zmq.Socket, frames: list[bytes], timeout_s: float = 2.0):
    sock.send_multipart(frames)
    assert sock.poll(int(timeout_s * 1000)), f"no answer within {timeout_s} s"
    return decode(sock.recv_multipart())


def one_executor_table() -> RoutingTable:
    return RoutingTable(version=1, models={"toy-a": INFO}, routes={"toy-a": ["ex0"]}, executors=["ex0"])


# ----------------------------------------------------------------------------- 1: a stalled executor


def test_a_stalled_executor_does_not_stall_the_router(tmp_path):
    """ex0 never reads: once its queue is full, requests for it get OVERLOADED at once, everyone else is served."""
    n = 5000
    with RouterThread(tmp_path, one_executor_table(), request_timeout_s=1.0) as rt:
        rt.executor(b"ex0", rcvhwm=10)  # connected, never reads
        flood, pinger = rt.robot(b"flood"), rt.robot(b"pinger")
        for i in range(n):
            flood.send_multipart(infer_frames(f"f{i}"))
        time.sleep(0.5)  # the router is now working through the flood
        t0 = time.monotonic()
        pong = ask(pinger, [pack_header({"v": 1, "kind": "ping", "id": "p"})], timeout_s=1.0)
        assert pong.id == "p" and time.monotonic() - t0 < 1.0
        assert isinstance(ask(rt.robot(b"new"), [pack_header({"kind": "hello", "id": "h"})], 1.0), Metadata)

        codes: Counter[str] = Counter()
        ids = set()
        end = time.monotonic() + 6  # the ones ex0's queue took expire after request_timeout_s
        while len(ids) < n and time.monotonic() < end:
            if flood.poll(200):
                rep = decode(flood.recv_multipart())
                assert isinstance(rep, ErrorReply)
                ids.add(rep.id)
                codes[rep.code.value] += 1
        assert len(ids) == n, f"{n - len(ids)} flooded requests got no answer; {codes}"
        assert codes["OVERLOADED"] > 0 and set(codes) <= {"OVERLOADED", "UNAVAILABLE"}, codes
        # The ones that reached ex0's queue were answered when they timed out, not silently dropped.
        assert not rt.router.in_flight


def test_a_robot_flooding_requests_is_refused_beyond_its_share_and_others_are_served(tmp_path):
    """One robot sends 200 requests at once to an executor that holds them: only max_in_flight_per_robot are
    forwarded, the rest answered OVERLOADED at once, and another robot's request still reaches the executor. Before,
    all 200 went into the executor's queue (a runaway client filled the model's queues; others got OVERLOADED)."""
    with RouterThread(tmp_path, one_executor_table(), request_timeout_s=60.0, max_in_flight_per_robot=8) as rt:
        ex = rt.executor(b"ex0")
        flood, other = rt.robot(b"flood"), rt.robot(b"other")
        for i in range(200):
            flood.send_multipart(infer_frames(f"f{i}"))
        refused = set()
        while len(refused) < 192 and flood.poll(2000):
            rep = decode(flood.recv_multipart())
            assert isinstance(rep, ErrorReply) and rep.code == ErrorCode.OVERLOADED, rep
            assert "8 requests in flight" in rep.message, rep.message
            refused.add(rep.id)
        assert len(refused) == 192 and not flood.poll(300)
        forwarded = []
        while ex.poll(300):
            forwarded.append(decode(ex.recv_multipart()[1:]).id)
        assert sorted(forwarded) == sorted(f"f{i}" for i in range(200) if f"f{i}" not in refused)
        other.send_multipart(infer_frames("o1"))
        assert ex.poll(2000) and decode(ex.recv_multipart()[1:]).id == "o1"
        # An answer gives the flooding robot room for one more.
        actions = np.zeros((INFO.horizon, INFO.action_dim), np.float32)
        ex.send_multipart([b"flood", *encode(InferReply(id=forwarded[0], model="toy-a", actions=actions))])
        assert isinstance(decode(flood.recv_multipart()), InferReply)
        flood.send_multipart(infer_frames("f-next"))
        assert ex.poll(2000) and decode(ex.recv_multipart()[1:]).id == "f-next"
        assert rt.router.in_flight.per_robot == {b"flood": 8, b"other": 1}


def test_a_full_executor_falls_back_to_another(tmp_path):
    """ex0 stops reading: once its queue is full, its share of the traffic goes to ex1, nothing is refused."""
    table = RoutingTable(version=1, models={"toy-a": INFO}, routes={"toy-a": ["ex0", "ex1"]}, executors=["ex0", "ex1"])
    # One robot connection stands for a fleet here: no cap on its own requests in flight. No ZeroMQ heartbeats: an
    # executor whose connection stays full for 3 s is closed by them and its requests answered UNAVAILABLE
    # (test_router_keepalive), which is not what this test is about.
    with RouterThread(tmp_path, table, max_in_flight_per_robot=10_000, keepalive_s=0) as rt:
        rt.executor(b"ex0", rcvhwm=10)  # never reads
        rt.answering_executor(b"ex1")
        robot = rt.robot(b"arm")
        n = 5000
        got: Counter[str] = Counter()

        def answers(wait_ms: int) -> None:
            while robot.poll(wait_ms):
                rep = decode(robot.recv_multipart())
                got["ok" if isinstance(rep, InferReply) else rep.code.value] += 1

        # In bursts of 250 with ex1's answers taken between them: 4000 at once could outrun ex1's connection on a
        # busy 2-core host (the router's send queue to it holds 1000), and the router rightly answered the rest
        # OVERLOADED, which is not what this test is about.
        for burst in range(0, n, 250):
            for i in range(burst, burst + 250):
                robot.send_multipart(infer_frames(f"r{i}"))
            answers(100)
        answers(1000)  # until answers stop coming: the rest wait in ex0's queue (30 s timeout)
        queued = len(rt.router.in_flight)
        assert got["ok"] + queued == n and set(got) == {"ok"}, (got, queued)
        assert got["ok"] > queued, (got, queued)  # ex1 took what ex0's full queue could not


def in_flight_gauge(rt: RouterThread) -> float | None:
    return rt.router.metrics.registry.get_sample_value("robion_router_in_flight_requests")


def test_the_in_flight_gauge_falls_when_requests_time_out(tmp_path):
    """Requests the router answers UNAVAILABLE at request_timeout_s leave the in-flight gauge too."""
    n = 3
    with RouterThread(tmp_path, one_executor_table(), request_timeout_s=0.5) as rt:
        rt.executor(b"ex0")  # connected, never answers
        robot = rt.robot(b"arm")
        for i in range(n):
            robot.send_multipart(infer_frames(f"t{i}"))
        end = time.monotonic() + 5
        while in_flight_gauge(rt) != n and time.monotonic() < end:
            time.sleep(0.01)
        assert in_flight_gauge(rt) == n
        codes = []
        while len(codes) < n and robot.poll(3000):
            rep = decode(robot.recv_multipart())
            assert isinstance(rep, ErrorReply)
            codes.append(rep.code)
        assert codes == [ErrorCode.UNAVAILABLE] * n
        end = time.monotonic() + 2  # the router loop sets the gauge; this thread only reads it
        while in_flight_gauge(rt) != 0 and time.monotonic() < end:
            time.sleep(0.01)
        assert not rt.router.in_flight
        assert in_flight_gauge(rt) == 0, "the gauge still counts the timed-out requests"


# ----------------------------------------------------------------------------- 2: no executor != unknown model


def test_state_lists_every_configured_model_while_unhosted(tmp_path):
    path, _ = cluster_config(tmp_path)  # ex0: toy-a, toy-b; ex1: toy-a
    state = ClusterState(load_config(path))
    state.replace_config(state.cfg)  # what the control plane publishes before any executor registers
    # Nothing registered yet: no description to give, but both names are in the table.
    assert state.table.models == {} and state.table.routes == {"toy-a": [], "toy-b": []}
    state.register("ex0", "cpu", {"toy-a": INFO, "toy-b": INFO}, now=100.0)
    state.register("ex1", "cpu", {"toy-a": INFO}, now=100.0)
    assert state.table.routes == {"toy-a": ["ex0", "ex1"], "toy-b": ["ex0"]}
    state.set_draining("ex0", True)
    assert set(state.table.models) == {"toy-a", "toy-b"}  # toy-b has no route but is still served
    assert state.table.routes == {"toy-a": ["ex1"]}
    assert state.table.executors == ["ex0", "ex1"]
    state.expire(now=100.0 + state.timeout_s + 1)  # both crash
    assert set(state.table.models) == {"toy-a", "toy-b"} and state.table.routes == {}
    # Only configured models are kept: an unconfigured replica's model goes when the replica goes.
    state.register("replica-9", "cpu", {"toy-x": INFO}, now=200.0)
    assert "toy-x" in state.table.models
    state.deregister("replica-9")
    assert set(state.table.models) == {"toy-a", "toy-b"}
    # The table survives its wire form unchanged (empty routes included).
    assert RoutingTable.from_wire(state.table.to_wire()) == state.table


def test_router_answers_unavailable_for_a_drained_model_and_unknown_only_for_unconfigured(tmp_path):
    with RouterThread(tmp_path) as rt:
        state = ClusterState(rt.cfg)
        state.register("ex0", "cpu", {"toy-a": INFO, "toy-b": INFO})
        state.set_draining("ex0", True)
        # Serve that table on the control plane's address, as the control plane would.
        ctl = rt.ctx.socket(zmq.ROUTER)
        ctl.setsockopt(zmq.LINGER, 0)
        ctl.bind(rt.cfg.control.bind)
        rt.socks.append(ctl)
        assert ctl.poll(3000), "the router did not ask for the routing table"
        peer, msg = ctl.recv_multipart()
        assert control.unpack(msg)["kind"] == "table_get"
        ctl.send_multipart([peer, control.pack("table", table=state.table.to_wire())])
        robot = rt.robot(b"arm")
        end = time.monotonic() + 3
        while time.monotonic() < end:
            meta = ask(robot, [pack_header({"kind": "hello", "id": "h"})])
            if meta.models:
                break
            time.sleep(0.05)
        assert set(meta.models) == {"toy-a", "toy-b"}, "a drained model must stay listed"
        for model in ("toy-a", "toy-b"):
            rep = ask(robot, infer_frames(f"q-{model}", model=model))
            assert isinstance(rep, ErrorReply) and rep.code == ErrorCode.UNAVAILABLE, rep
        rep = ask(robot, infer_frames("q-ghost", model="ghost"))
        assert rep.code == ErrorCode.UNKNOWN_MODEL


def test_router_counts_an_empty_route_as_served(tmp_path):
    """Before any executor described a configured model, the table has only its (empty) route."""
    table = RoutingTable(version=1, models={}, routes={"toy-a": []}, executors=[])
    with RouterThread(tmp_path, table) as rt:
        robot = rt.robot(b"arm")
        assert ask(robot, infer_frames("a", model="toy-a")).code == ErrorCode.UNAVAILABLE
        assert ask(robot, infer_frames("b", model="toy-z")).code == ErrorCode.UNKNOWN_MODEL


def test_router_without_a_table_counts_its_configured_models_as_served(tmp_path):
    """A router that has no table yet (the control plane is starting, holding its first table back until the
    executors register, or down since the router started) answered every configured model UNKNOWN_MODEL,
    "never retry": robots of a cluster coming up gave up on models it was about to serve."""
    with RouterThread(tmp_path) as rt:  # no control plane listens: the router never gets a table
        robot = rt.robot(b"arm")
        rep = ask(robot, infer_frames("a", model="toy-a"))
        assert isinstance(rep, ErrorReply) and rep.code == ErrorCode.UNAVAILABLE, rep
        assert ask(robot, infer_frames("b", model="toy-b")).code == ErrorCode.UNAVAILABLE
        assert ask(robot, infer_frames("c", model="toy-z")).code == ErrorCode.UNKNOWN_MODEL
        assert rt.router.routing.table.version == 0
        counted = rt.router.metrics.registry.get_sample_value(
            "robion_router_requests_total", {"model": "toy-a", "status": "unavailable"})
        assert counted == 1.0


# ----------------------------------------------------------------------------- 3: frames per message


def test_messages_with_more_frames_than_their_kind_carries_are_refused(tmp_path):
    with RouterThread(tmp_path, one_executor_table()) as rt:
        rt.answering_executor(b"ex0")
        robot = rt.robot(b"arm")
        many = infer_frames("many") + [b"\0" * 100] * 2000  # 224 KB in all, under the size limit: too many frames
        rep = ask(robot, many)
        assert isinstance(rep, ErrorReply) and rep.code == ErrorCode.BAD_REQUEST and rep.id == "many", rep
        assert "at most 4" in rep.message, rep  # refused by the router, not passed on to the executor
        # Header, two cameras and a state frame is the most a toy-a request can have; one more is refused here.
        rep = ask(robot, infer_frames("plus2") + [b"x", b"y"])
        assert rep.code == ErrorCode.BAD_REQUEST and "at most 4" in rep.message, rep
        rep = ask(robot, [pack_header({"kind": "ping", "id": "p2"}), b"x"])
        assert rep.code == ErrorCode.BAD_REQUEST and rep.id == "p2"
        # A message of an unknown kind is bounded by the protocol-wide maximum.
        rep = ask(robot, [pack_header({"kind": "teleport", "id": "t"})] + [b""] * MAX_FRAMES)
        assert rep.code == ErrorCode.BAD_REQUEST and "frames" in rep.message
        # The router keeps serving: a ping and a valid request still go through.
        assert ask(robot, [pack_header({"kind": "ping", "id": "p3"})]).id == "p3"
        assert isinstance(ask(robot, infer_frames("ok")), InferReply)


# ----------------------------------------------------------------------------- 4: ids and versions


def test_ids_are_echoed_exactly_and_bad_ids_refused(tmp_path):
    with RouterThread(tmp_path, one_executor_table()) as rt:
        rt.answering_executor(b"ex0")
        robot = rt.robot(b"arm")
        rep = ask(robot, infer_frames(5))
        assert isinstance(rep, InferReply) and rep.id == 5 and type(rep.id) is int
        assert ask(robot, [pack_header({"kind": "ping", "id": 0})]).id == 0
        assert ask(robot, [pack_header({"kind": "hello", "id": 2**63})]).id == 2**63
        long_ok = "a" * 256
        assert ask(robot, infer_frames(long_ok)).id == long_ok
        for bad in ("a" * 300, True, 1.5, ["x"], {"a": 1}, b"raw"):
            rep = ask(robot, infer_frames(bad))
            assert isinstance(rep, ErrorReply) and rep.code == ErrorCode.BAD_REQUEST and rep.id == "", (bad, rep)
            assert rep.message.startswith("id:"), rep
        rep = ask(robot, [pack_header({"kind": "ping", "id": "b" * 257})])
        assert rep.code == ErrorCode.BAD_REQUEST


def test_int_and_str_ids_with_the_same_digits_are_different_requests(tmp_path):
    with RouterThread(tmp_path, one_executor_table()) as rt:
        rt.answering_executor(b"ex0", hold=2)  # both are in flight together
        robot = rt.robot(b"arm")
        robot.send_multipart(infer_frames(7))
        robot.send_multipart(infer_frames("7"))
        got = []
        for _ in range(2):
            assert robot.poll(3000)
            got.append(decode(robot.recv_multipart()))
        assert all(isinstance(r, InferReply) for r in got), got
        assert sorted((type(r.id).__name__, r.id) for r in got) == [("int", 7), ("str", "7")]
        # A true duplicate is still refused while the first is in flight.
        robot.send_multipart(infer_frames(8))
        rep = ask(robot, infer_frames(8))
        assert rep.code == ErrorCode.BAD_REQUEST and "already in flight" in rep.message and rep.id == 8


@pytest.mark.parametrize("v", [2, 99, True, 1.0, "1", None])
def test_a_wrong_version_is_refused_on_every_kind(tmp_path, v):
    with RouterThread(tmp_path, one_executor_table()) as rt:
        robot = rt.robot(b"arm")
        for frames in ([pack_header({"v": v, "kind": "hello", "id": "h"})],
                       [pack_header({"v": v, "kind": "ping", "id": "p"})],
                       infer_frames("i", v=v)):
            rep = ask(robot, frames)
            assert isinstance(rep, ErrorReply) and rep.code == ErrorCode.BAD_REQUEST, (v, rep)
            assert rep.message.startswith("v:")
        # v: 1 and no v at all are both fine.
        assert isinstance(ask(robot, [pack_header({"v": 1, "kind": "hello", "id": "h"})]), Metadata)
        assert ask(robot, [pack_header({"kind": "ping", "id": "p"})]).id == "p"


def test_decode_keeps_id_types_and_checks_v_and_id():
    frames = [bytes(f) for f in encode(InferReply(id=7, model="m", actions=np.zeros((2, 2), np.float32)))]
    assert decode(frames).id == 7
    assert decode(encode(ErrorReply("7", ErrorCode.INTERNAL, "x"))).id == "7"
    for header in ({"v": True, "kind": "ping", "id": "p"}, {"v": 2, "kind": "ping", "id": "p"},
                   {"kind": "ping", "id": False}, {"kind": "ping", "id": "x" * 257}, {"kind": "ping", "id": 1.0}):
        with pytest.raises(ProtocolError) as e:
            decode([pack_header(header)])
        assert e.value.code == ErrorCode.BAD_REQUEST


def test_deeply_nested_header_values_are_answered_bad_request(tmp_path):
    """repr() of a list nested a thousand deep raises RecursionError: quoted in an error message, it took the
    router's handling of the message down, and the robot got no answer at all."""
    v: list = []
    for _ in range(1000):
        v = [v]
    with RouterThread(tmp_path, one_executor_table()) as rt:
        robot = rt.robot(b"arm")
        for rid, header in (("k", {"v": 1, "kind": v, "id": "k"}), ("v", {"v": v, "kind": "ping", "id": "v"})):
            rep = ask(robot, [pack_header(header)])
            assert isinstance(rep, ErrorReply) and rep.code == ErrorCode.BAD_REQUEST and rep.id == rid, rep
        assert ask(robot, [pack_header({"v": 1, "kind": "ping", "id": "p"})]).id == "p"


def test_a_request_whose_handling_fails_is_answered_internal_at_once(tmp_path, monkeypatch):
    """A fault inside the router's handling of one request (injected here: no input is known to cause one) is
    answered INTERNAL ("retry") at once, instead of leaving the robot to wait out its timeout; the next
    request is routed as before."""
    with RouterThread(tmp_path, one_executor_table(), request_timeout_s=60.0) as rt:
        ex = rt.executor(b"ex0")
        robot = rt.robot(b"arm")
        routing = rt.router.routing
        real = routing.candidates
        faults = iter([True])

        def candidates(model, pin):
            if next(faults, False):
                raise RuntimeError("injected fault")
            return real(model, pin)

        monkeypatch.setattr(routing, "candidates", candidates)
        reg = rt.router.metrics.registry
        rep = ask(robot, infer_frames("r1"))
        assert isinstance(rep, ErrorReply) and rep.code == ErrorCode.INTERNAL and rep.id == "r1", rep
        assert not rt.router.in_flight
        # Counted under its model, a miss, as the router's other answers are (it was in no SLO series, under "").
        assert reg.get_sample_value("robion_router_slo_missed_total", {"model": "toy-a"}) == 1.0
        assert reg.get_sample_value("robion_router_requests_total", {"model": "toy-a", "status": "internal"}) == 1.0
        robot.send_multipart(infer_frames("r2"))
        assert ex.poll(2000), "the next request never reached the executor"
        assert decode(ex.recv_multipart()[1:]).id == "r2"


def test_the_routers_slo_counters_count_every_answer_its_own_included(tmp_path):
    """The SLO counters operators read were the executors' alone: a request the router answered itself (the executor
    stalled, timed out, restarted or gone) reached none, and the dashboard read near 100% while robots failed. The
    router's count every request for a served model; the series exist at 0 before any request."""
    with RouterThread(tmp_path, one_executor_table(), request_timeout_s=0.3) as rt:
        reg = rt.router.metrics.registry

        def slo(kind: str, model: str = "toy-a") -> float | None:
            return reg.get_sample_value(f"robion_router_slo_{kind}_total", {"model": model})

        assert (slo("met"), slo("missed"), slo("met", "toy-b")) == (0.0, 0.0, 0.0)
        stalled = rt.executor(b"ex0")  # connected, never answers
        robot = rt.robot(b"arm")
        rep = ask(robot, infer_frames("late"), timeout_s=5.0)
        assert isinstance(rep, ErrorReply) and rep.code == ErrorCode.UNAVAILABLE
        assert (slo("met"), slo("missed")) == (0.0, 1.0)
        stalled.close()
        rt.socks.remove(stalled)
        rt.answering_executor(b"ex0")
        assert isinstance(ask(robot, infer_frames("ok")), InferReply)
        assert isinstance(ask(robot, infer_frames("bad", model="nope")), ErrorReply)  # not served: no series
        assert (slo("met"), slo("missed"), slo("met", "nope")) == (1.0, 1.0, None)


def test_a_reply_is_judged_by_the_deadline_its_request_was_sent_under(tmp_path):
    """A reply arriving after an apply took its model out of the table counted met however late it was (the deadline
    was read from the table of the reply's time, and a model not in it had none)."""
    with RouterThread(tmp_path, one_executor_table(), request_timeout_s=60.0) as rt:
        reg = rt.router.metrics.registry
        ex = rt.executor(b"ex0")
        robot = rt.robot(b"arm")
        robot.send_multipart(infer_frames("r1"))
        assert ex.poll(2000)
        robot_id, *body = ex.recv_multipart()
        req = decode(body)
        # An apply drops toy-a; ex0 stays (it serves toy-b).
        rt.router.routing.update(RoutingTable(version=2, models={"toy-b": INFO}, routes={"toy-b": ["ex0"]},
                                              executors=["ex0"]))
        time.sleep(INFO.deadline_ms / 1e3 + 0.2)
        ex.send_multipart([robot_id, *encode(InferReply(id=req.id, model=req.model,
                                                        actions=np.zeros((10, 7), np.float32)))])
        assert robot.poll(2000) and isinstance(decode(robot.recv_multipart()), InferReply)
        assert reg.get_sample_value("robion_router_slo_met_total", {"model": "toy-a"}) == 0.0
        assert reg.get_sample_value("robion_router_slo_missed_total", {"model": "toy-a"}) == 1.0


def test_the_routers_own_refusals_of_a_served_models_requests_count_under_it(tmp_path):
    """Too many frames, a message over the size limit and an unusable id were counted under model "" and missing
    from the served model's SLO series (docs/operations.md: "" is for a model that is not served), so a fleet sending
    oversized images showed no SLO misses. The executor counts such refusals under the model; so does the router."""
    with RouterThread(tmp_path, one_executor_table(), max_message_bytes=100_000) as rt:
        reg = rt.router.metrics.registry
        robot = rt.robot(b"arm")
        refused = [infer_frames("many") + [b"x", b"y"],
                   infer_frames("big")[:1] + [b"\0" * 60_000] * 2,
                   infer_frames(""),
                   infer_frames("bad-v", v=99)]
        for frames in refused:
            assert isinstance(ask(robot, frames), ErrorReply)
        assert reg.get_sample_value("robion_router_slo_missed_total", {"model": "toy-a"}) == len(refused)
        assert reg.get_sample_value("robion_router_requests_total", {"model": "", "status": "bad_request"}) is None
        assert reg.get_sample_value("robion_router_requests_total", {"model": "toy-a", "status": "too_large"}) == 1
        # A model the cluster does not serve still gets no series of its own.
        assert isinstance(ask(robot, infer_frames("nope", model="nope")[:1] + [b"\0" * 60_000] * 2), ErrorReply)
        assert reg.get_sample_value("robion_router_requests_total", {"model": "", "status": "too_large"}) == 1
        assert reg.get_sample_value("robion_router_slo_missed_total", {"model": "nope"}) is None
