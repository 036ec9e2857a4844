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
