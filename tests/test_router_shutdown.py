"""The router process at shutdown: every request in flight still gets its one answer.

A real router process (services.router.main) and a real control plane on loopback; the executor is a
stand-in registered with the control plane that takes requests and never answers.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import zmq

from shared.cluster import control_request
from shared.protocol import ErrorCode, ErrorReply, decode, pack_header
from tests.helpers import cluster_config, start_control_plane
from tests.test_router_robustness import INFO, infer_frames

ROOT = Path(__file__).resolve().parent.parent


def test_requests_in_flight_are_answered_when_the_router_stops(tmp_path):
    path, data = cluster_config(tmp_path)
    cfg, cp_stop, cp_thread = start_control_plane(path, data)
    # ex0, the test's executor socket, registers toy-a: the control plane's table routes it there.
    reply = control_request(cfg.control.bind, "register", timeout_s=5, executor="ex0", device="cpu", instance="i0",
                            models={"toy-a": INFO.to_wire()})
    assert reply is not None and reply["kind"] == "registered", reply
    ctx = zmq.Context()
    proc = subprocess.Popen([sys.executable, "-m", "services.router.main", "-c", str(path), "--log-level", "WARNING"],
                            cwd=ROOT, stderr=subprocess.PIPE, text=True)
    executor = ctx.socket(zmq.DEALER)
    robot = ctx.socket(zmq.DEALER)
    try:
        executor.setsockopt(zmq.IDENTITY, b"ex0")
        executor.setsockopt(zmq.LINGER, 0)
        executor.connect(cfg.router.backend)
        robot.setsockopt(zmq.LINGER, 0)
        robot.connect(cfg.router.bind)
        # Until the router is up and routes by the table, a request is refused (or not read at all):
        # send fresh ones until one reaches the executor.
        held = None
        end = time.monotonic() + 20
        i = 0
        while held is None and time.monotonic() < end:
            executor.send_multipart([b"", pack_header({"kind": "executor_hello", "executor": "ex0"})])
            robot.send_multipart(infer_frames(f"warm-{i}"))
            i += 1
            if executor.poll(300):
                held = decode(executor.recv_multipart()[1:]).id  # never answered
            while robot.poll(0):
                robot.recv_multipart()  # refusals from before the table arrived
        assert held is not None, "no request reached the executor"

        proc.send_signal(signal.SIGTERM)
        assert robot.poll(5000), "the request in flight got no answer when the router stopped"
        rep = decode(robot.recv_multipart())
        assert isinstance(rep, ErrorReply) and rep.code == ErrorCode.UNAVAILABLE and rep.id == held, rep
        assert "shutting down" in rep.message
        assert proc.wait(10) == 0, proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        cp_stop.set()
        cp_thread.join(10)
        for s in (executor, robot):
            s.close(linger=0)
        ctx.term()


def test_requests_not_read_yet_are_answered_when_the_router_stops(tmp_path, monkeypatch):
    """Requests already waiting in the robots' socket when the router stopped were dropped with it: their robots each
    waited out their own timeout (in a reviewer's run, 1925 of 2000 sent in a burst got no answer at all). The router
    answers them UNAVAILABLE ("retry") as it answers those in flight."""
    import threading

    from services.router.frontend import Router
    from tests.test_router_robustness import RouterThread, one_executor_table

    first_seen = threading.Event()
    real = Router._from_robot

    def slow_from_robot(self, frames):
        # The first request holds the loop until the stop: the rest of the burst stays unread in the socket.
        if not first_seen.is_set():
            first_seen.set()
            rt.stop.wait(10)
        real(self, frames)

    monkeypatch.setattr(Router, "_from_robot", slow_from_robot)
    with RouterThread(tmp_path, one_executor_table()) as rt:
        robot = rt.robot(b"arm")
        ids = [f"r{i}" for i in range(600)]  # more than one turn of the loop reads (256) before it sees the stop
        for rid in ids:
            robot.send_multipart(infer_frames(rid))
        assert first_seen.wait(10)
        time.sleep(0.3)  # the burst is in the router's socket
        rt.stop.set()
        rt.thread.join(10)
        answers = {}
        while robot.poll(2000):
            msg = decode(robot.recv_multipart())
            answers[msg.id] = msg
        assert sorted(answers) == sorted(ids), f"{len(answers)} of {len(ids)} answered"
        assert all(isinstance(m, ErrorReply) and m.code == ErrorCode.UNAVAILABLE for m in answers.values())
