"""An executor that restarts under the same name: its requests in flight are answered at once.

The router's backend has ROUTER_HANDOVER, so a new process with the old one's name (ZeroMQ
identity) simply takes over the name; the router only learns of the restart from the new
process's ``executor_hello``, which carries a per-process ``instance`` token. Requests sent to
the old process must then get UNAVAILABLE at once rather than after ``router.request_timeout_s``.

The router runs its real loop in a thread (RouterThread); the executors are DEALER sockets with
the executor's identity, speaking the real control encoding. The last test checks that a real
ExecutorIO says hello with its instance.
"""

from __future__ import annotations

import logging
import socket
import struct
import threading
import time

import numpy as np
import pytest
import zmq

from services.router import frontend
from shared import control
from shared.control import RoutingTable
from shared.protocol import ErrorCode, ErrorReply, InferReply, decode, encode
from tests.test_executor_io import Harness
from tests.test_router_robustness import INFO, RouterThread, infer_frames, one_executor_table

LONG_TIMEOUT_S = 60.0  # far beyond any wait below: an answer that comes at all came from the restart
OLD, NEW = "a" * 32, "b" * 32  # instance tokens (uuid4().hex in the executor)


def hello(sock: zmq.Socket, **fields) -> None:
    sock.send_multipart([b"", control.pack("executor_hello", executor="ex0", **fields)])


def held_request(rt: RouterThread, robot: zmq.Socket, executor: zmq.Socket, rid: str, model: str = "toy-a") -> None:
    """Send ``rid`` and wait until the router has forwarded it to ``executor``, which never answers."""
    robot.send_multipart(infer_frames(rid, model))
    while True:
        assert executor.poll(2000), "the request never reached the executor"
        frames = executor.recv_multipart()
        if frames != [b""]:  # not the router's probe of the connection (after another executor's closed)
            break
    assert decode(frames[1:]).id == rid


def unavailable_answers(robot: zmq.Socket, ids: set[str], t0: float, reasons: tuple[str, ...]) -> None:
    """The answers to ``ids`` arrive within 2 s of ``t0``, each UNAVAILABLE for one of ``reasons``."""
    answers = {}
    while len(answers) < len(ids) and robot.poll(3000):
        rep = decode(robot.recv_multipart())
        answers[rep.id] = rep
    took = time.monotonic() - t0
    assert set(answers) == ids, f"got {answers} within {took:.1f} s"
    for rep in answers.values():
        assert isinstance(rep, ErrorReply) and rep.code == ErrorCode.UNAVAILABLE, rep
        assert any(r in rep.message for r in reasons), rep.message
    assert took < 2.0


def assert_no_answer(robot: zmq.Socket, wait_s: float = 0.5) -> None:
    if robot.poll(int(wait_s * 1000)):
        raise AssertionError(f"unexpected answer {decode(robot.recv_multipart())}")


@pytest.mark.parametrize("old_process", ["still connected", "gone"])
def test_requests_to_a_restarted_executor_are_answered_at_once(tmp_path, old_process):
    """"still connected": the new process takes the name over from a hung one (ROUTER_HANDOVER);
    "gone": the old one crashed first. Either way the router cannot tell from its socket."""
    with RouterThread(tmp_path, one_executor_table(), request_timeout_s=LONG_TIMEOUT_S) as rt:
        old = rt.executor(b"ex0")
        hello(old, instance=OLD)
        robot = rt.robot(b"arm")
        held_request(rt, robot, old, "r1")
        held_request(rt, robot, old, "r2")
        if old_process == "gone":
            old.close(linger=0)

        new = rt.executor(b"ex0")
        t0 = time.monotonic()
        hello(new, instance=NEW)
        # A crashed process's closed connection may be seen before its successor's hello.
        reasons = ("ex0 restarted", "ex0 closed its connection") if old_process == "gone" else ("ex0 restarted",)
        unavailable_answers(robot, {"r1", "r2"}, t0, reasons)
        assert not rt.router.in_flight

        # The new process serves what comes next, and its answers reach the robot.
        held_request(rt, robot, new, "r3")
        assert_no_answer(robot)  # nothing else was failed by the restart


def test_requests_to_an_executor_whose_connection_closed_are_answered_at_once(tmp_path):
    """An executor crashes (its connection closes) while the control plane is away, so no new table will drop it:
    its requests in flight are answered UNAVAILABLE at once, not after request_timeout_s. Another executor's held
    request, its connection up, is left to be answered."""
    table = RoutingTable(version=1, models={"toy-a": INFO, "toy-b": INFO}, routes={"toy-a": ["ex0"], "toy-b": ["ex1"]},
                         executors=["ex0", "ex1"])
    with RouterThread(tmp_path, table, request_timeout_s=LONG_TIMEOUT_S) as rt:
        crashing, alive = rt.executor(b"ex0"), rt.executor(b"ex1")
        robot = rt.robot(b"arm")
        held_request(rt, robot, crashing, "r1")
        held_request(rt, robot, crashing, "r2")
        held_request(rt, robot, alive, "r3", "toy-b")
        t0 = time.monotonic()
        crashing.close(linger=0)
        unavailable_answers(robot, {"r1", "r2"}, t0, ("ex0 closed its connection",))
        assert_no_answer(robot, 1.5)  # r3's executor is connected: the probes left it alone
        assert list(rt.router.in_flight) and all(f.executor == "ex1" for f in rt.router.in_flight.values())
        # and it still answers r3 through the router (after skipping the probes it was sent)
        while alive.poll(100):
            assert alive.recv_multipart() == [b""]
        actions = np.zeros((INFO.horizon, INFO.action_dim), np.float32)
        alive.send_multipart([b"arm", *encode(InferReply(id="r3", model="toy-b", actions=actions))])
        assert robot.poll(2000)
        assert isinstance(decode(robot.recv_multipart()), InferReply)


class ResettingProxy:
    """A TCP proxy in front of the router's backend whose connections can be reset (a network blip) or frozen (a
    peer that went silent without closing anything: a stopped process, a dead host)."""

    def __init__(self, upstream_port: int):
        self.upstream = upstream_port
        self.frozen: set[socket.socket] = set()  # sockets whose bytes are held (freeze)
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.pairs: list[tuple[socket.socket, socket.socket]] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            upstream = socket.create_connection(("127.0.0.1", self.upstream))
            self.pairs.append((client, upstream))
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    def _pump(self, a: socket.socket, b: socket.socket) -> None:
        try:
            while data := a.recv(65536):
                while a in self.frozen:  # hold the bytes: nothing passes, nothing closes
                    time.sleep(0.01)
                b.sendall(data)
        except OSError:
            pass

    def freeze(self) -> None:
        """Stop passing bytes on the connections made so far, both ways; a connection made later passes them."""
        self.frozen.update(s for pair in self.pairs for s in pair)

    def reset(self) -> None:
        for pair in self.pairs:
            for s in pair:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # close with a RST
                # shutdown first: it wakes the pump blocked in recv(), which a bare close() leaves reading a reused fd
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()
        self.pairs = []

    def close(self) -> None:
        self.reset()
        self.listener.close()


def executor_behind_proxy(rt: RouterThread) -> tuple[ResettingProxy, zmq.Socket]:
    """A stand-in executor ex0 connected to the router's backend through a ResettingProxy."""
    proxy = ResettingProxy(int(rt.cfg.router.backend.rsplit(":", 1)[1]))
    ex = rt.ctx.socket(zmq.DEALER)
    ex.setsockopt(zmq.IDENTITY, b"ex0")
    ex.setsockopt(zmq.LINGER, 0)
    ex.connect(f"tcp://127.0.0.1:{proxy.port}")
    rt.socks.append(ex)
    ex.send(b"")  # the router ignores a one-frame message; its handshake makes the identity routable
    time.sleep(0.3)
    return proxy, ex


def test_an_executor_whose_connection_resets_and_comes_back_still_answers(tmp_path, monkeypatch):
    """A living executor's TCP connection resets (a network blip): its DEALER reconnects at once, still holding its
    requests, and answers them on the new connection. The router's probe after the disconnect failed them at the first
    unreachable probe and dropped the answer; now only an executor unreachable for RECONNECT_GRACE_S is failed. (The
    grace is raised here for a loaded test host; the code before failed at the first probe whatever the grace.)"""
    monkeypatch.setattr(frontend, "RECONNECT_GRACE_S", 2.0, raising=False)
    monkeypatch.setattr(frontend, "PROBE_AFTER_DISCONNECT_S", 4.0)
    with RouterThread(tmp_path, one_executor_table(), request_timeout_s=LONG_TIMEOUT_S) as rt:
        proxy, ex = executor_behind_proxy(rt)
        try:
            robot = rt.robot(b"arm")
            held_request(rt, robot, ex, "r1")
            proxy.reset()
            time.sleep(1.5)  # the executor computes; its DEALER reconnects meanwhile
            actions = np.zeros((INFO.horizon, INFO.action_dim), np.float32)
            ex.send_multipart([b"arm", *encode(InferReply(id="r1", model="toy-a", actions=actions))])
            assert robot.poll(5000), "no answer"
            rep = decode(robot.recv_multipart())
            assert isinstance(rep, InferReply) and rep.id == "r1", rep
        finally:
            proxy.close()


@pytest.mark.parametrize("second", ["same instance", "no instance"])
def test_a_hello_that_is_not_a_restart_fails_nothing(tmp_path, second):
    """The executor says hello again with its own instance when it re-registers; an executor from
    before the instance field says hello without one. Neither is a restart."""
    with RouterThread(tmp_path, one_executor_table(), request_timeout_s=LONG_TIMEOUT_S) as rt:
        ex = rt.executor(b"ex0")
        if second == "same instance":
            hello(ex, instance=OLD)
        else:
            hello(ex)
        robot = rt.robot(b"arm")
        held_request(rt, robot, ex, "r1")
        hello(ex, **({"instance": OLD} if second == "same instance" else {}))
        assert_no_answer(robot)
        assert len(rt.router.in_flight) == 1


def test_the_first_hello_of_a_name_fails_nothing(tmp_path):
    """A router that restarted itself (or missed the first hello) meets an executor with requests in
    flight: an instance it has not seen for that name is not a restart."""
    with RouterThread(tmp_path, one_executor_table(), request_timeout_s=LONG_TIMEOUT_S) as rt:
        ex = rt.executor(b"ex0")  # connects without a hello
        robot = rt.robot(b"arm")
        held_request(rt, robot, ex, "r1")
        hello(ex, instance=OLD)
        assert_no_answer(robot)
        assert len(rt.router.in_flight) == 1


@pytest.mark.parametrize("frame", [
    b"\xc1not msgpack",
    control.pack("executor_hello", executor="ex0", instance=7),
    control.pack("executor_hello", executor="ex0", instance=""),
    control.pack("something_else", executor="ex0"),
    b"\x93\x01\x02\x03",  # msgpack, but a list
    control.pack("executor_hello", executor="ex0", instance=OLD, pad=[{}] * 100_000),
], ids=["garbage", "instance not a str", "empty instance", "unknown kind", "not a map", "huge"])
def test_a_malformed_executor_hello_is_logged_once_and_ignored(tmp_path, caplog, monkeypatch, frame):
    monkeypatch.setattr(frontend, "WARN_EVERY_S", 60.0)  # one report for the whole test, however slow the host
    with RouterThread(tmp_path, one_executor_table(), request_timeout_s=LONG_TIMEOUT_S) as rt:
        ex = rt.executor(b"ex0")
        hello(ex, instance=OLD)
        robot = rt.robot(b"arm")
        held_request(rt, robot, ex, "r1")
        for _ in range(20):
            ex.send_multipart([b"", frame])
        assert_no_answer(robot)
        assert len(rt.router.in_flight) == 1
        # The router is unharmed: the executor's answer still reaches the robot.
        actions = np.zeros((INFO.horizon, INFO.action_dim), np.float32)
        ex.send_multipart([b"arm", *encode(InferReply(id="r1", model="toy-a", actions=actions))])
        assert robot.poll(2000)
        assert isinstance(decode(robot.recv_multipart()), InferReply)
    records = [r for r in caplog.records if r.name == "robion.router" and r.levelno >= logging.WARNING]
    assert len(records) == 1, [r.getMessage() for r in records]  # rate-limited, not one per message
    assert records[0].exc_info is None  # no traceback for what a peer sent


def test_an_executor_sending_a_frame_beyond_the_bound_is_disconnected(tmp_path):
    """The backend bounds frames as robots' port and the executors do: libzmq drops a connection that sends a larger
    one, unread (a living executor then redials). Without the bound the router took the frame whole (1 GB of memory
    for a 1 GB frame, 14 GB for a stream of them)."""
    from shared.service import monitor_events

    with RouterThread(tmp_path, one_executor_table(), request_timeout_s=LONG_TIMEOUT_S) as rt:
        ex = rt.executor(b"ex0")
        events = ex.get_monitor_socket(zmq.EVENT_DISCONNECTED)
        hello(ex, instance=OLD)
        robot = rt.robot(b"arm")
        held_request(rt, robot, ex, "r1")  # the connection is up and used
        ex.send_multipart([b"arm", b"\x80", b"\0" * (2 * rt.cfg.router.max_message_bytes + 65537)])
        assert events.poll(3000) and zmq.EVENT_DISCONNECTED in monitor_events(events), "the router kept the connection"
        ex.disable_monitor()
        events.close(linger=0)


def test_requests_an_executor_lost_with_its_old_connection_are_answered(tmp_path, monkeypatch):
    """The executor comes back on a new connection (a reset, or the router's heartbeat timeout after it froze): what
    was queued for it on the old one is gone. r1 (never answered) is answered UNAVAILABLE RECONNECT_ANSWER_S after the
    reconnect, where it waited request_timeout_s; r2, from before too but answered in time, and r3, sent after, are
    the executor's to answer."""
    monkeypatch.setattr(frontend, "RECONNECT_ANSWER_S", 1.0, raising=False)
    with RouterThread(tmp_path, one_executor_table(), request_timeout_s=LONG_TIMEOUT_S) as rt:
        ex = rt.executor(b"ex0")
        hello(ex, instance=OLD, connection=1)
        robot = rt.robot(b"arm")
        held_request(rt, robot, ex, "r1")
        held_request(rt, robot, ex, "r2")
        time.sleep(0.3)  # hellos of the same connection change nothing
        hello(ex, instance=OLD, connection=1)
        assert_no_answer(robot, 1.5)
        t0 = time.monotonic()
        hello(ex, instance=OLD, connection=2)
        time.sleep(0.3)  # read before r3 goes out (one forwarded before the hello is read counts as from before)
        held_request(rt, robot, ex, "r3")
        actions = np.zeros((INFO.horizon, INFO.action_dim), np.float32)
        ex.send_multipart([b"arm", *encode(InferReply(id="r2", model="toy-a", actions=actions))])
        assert isinstance(decode(robot.recv_multipart()), InferReply)
        unavailable_answers(robot, {"r1"}, t0, ("lost with its old connection",))
        assert time.monotonic() - t0 >= 0.9
        assert [k[2] for k in rt.router.in_flight] == ["r3"]
        assert_no_answer(robot, 1.5)  # r3 is left to the executor


def test_a_name_two_live_processes_share_is_reported(tmp_path, caplog, monkeypatch):
    """Two live processes under one name take it from each other whenever one redials, each passing for the other's
    restart. Which should serve cannot be told at the router (a frozen process back, a successor since gone), so no
    process is told to stop; the name's restarts are counted and reported, naming the likely cause."""
    monkeypatch.setattr(frontend, "WARN_EVERY_S", 60.0)
    with caplog.at_level(logging.WARNING, logger="robion.router"):
        with RouterThread(tmp_path, one_executor_table(), request_timeout_s=LONG_TIMEOUT_S) as rt:
            for i, instance in enumerate([OLD, NEW, OLD, NEW]):  # the first hello, then three "restarts"
                ex = rt.executor(b"ex0")
                hello(ex, instance=instance, connection=1)
                time.sleep(0.3)  # read before the next connection takes the name
                assert rt.router._instances["ex0"] == instance
                flapping = [r for r in caplog.records if "two processes may be running" in r.getMessage()]
                assert len(flapping) == (1 if i == 3 else 0), [r.getMessage() for r in caplog.records]


def test_the_executor_says_hello_with_its_instance(tmp_path):
    """A real ExecutorIO (toy model on the CPU): its hello names it and carries its process token."""
    hellos: list[list[bytes]] = []

    class Recording(Harness):
        def _wait_hello(self) -> None:
            assert self.router.poll(10_000), "the executor never said hello"
            hellos.append(self.router.recv_multipart())

    h = Recording(tmp_path)
    try:
        identity, robot, frame = hellos[0]
        assert identity == b"ex0" and robot == b""
        assert control.unpack(frame) == {"kind": "executor_hello", "executor": "ex0", "instance": h.io.instance}
        assert len(h.io.instance) == 32
    finally:
        h.close()


def test_the_executor_says_hello_before_its_engine_starts(tmp_path):
    """The connect takes the name over at the router at once (ROUTER_HANDOVER), so the hello that tells
    the router the old process is gone must come with it, not after the engine start (graph capture
    takes minutes on a GPU): an ExecutorIO that was only constructed has already said hello."""
    import torch

    from services.executor.hosting import EngineSlot, ModelStore
    from services.executor.transport import ExecutorIO
    from shared.config import load_config
    from shared.metrics import ExecutorMetrics
    from tests.helpers import bound_router, cluster_config

    path, _ = cluster_config(tmp_path)
    cfg = load_config(path)
    ctx = zmq.Context()
    router = bound_router(ctx, cfg.router.backend)
    store = ModelStore(torch.device("cpu"))
    hosted = store.load([cfg.model("toy-a")])
    slot = EngineSlot(cfg.engine, torch.device("cpu"), lambda results: None)  # never started
    io = ExecutorIO("ex0", cfg, "cpu", store, slot, hosted, ExecutorMetrics("ex0", "cpu", {"toy-a": 0.5}), context=ctx)
    try:
        assert router.poll(5000), "no hello before run()"
        identity, robot, frame = router.recv_multipart()
        assert identity == b"ex0" and robot == b""
        assert control.unpack(frame) == {"kind": "executor_hello", "executor": "ex0", "instance": io.instance}
    finally:
        io.close()
        router.close()
        ctx.term()
