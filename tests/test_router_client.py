"""The robot SDK against a real Router loop: every submitted request ends in exactly one outcome.

The router runs its real loop on loopback TCP (RouterThread); the executor is a DEALER the test
drives with the real protocol encoder, so replies can be held back, delayed or garbled.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zmq

from shared.client import MalformedReply, RequestTimeout, RobionError, RobotClient
from shared.protocol import ErrorCode, decode, pack_header
from tests.helpers import free_ports
from tests.test_router_robustness import INFO, RouterThread, one_executor_table

ROOT = Path(__file__).resolve().parent.parent


def observation() -> tuple[dict[str, np.ndarray], np.ndarray]:
    rng = np.random.default_rng(0)
    return ({c: rng.integers(0, 256, INFO.image_shape, dtype=np.uint8) for c in INFO.cameras},
            np.zeros(INFO.state_dim, np.float32))


def garbling_executor(rt: RouterThread, name: bytes, timings) -> None:
    """An executor whose replies are well-formed except for ``timings``."""
    sock = rt.executor(name, rcvhwm=0)

    def loop() -> None:
        while not rt.peers_stop.is_set():
            if not sock.poll(50):
                continue
            robot, *body = sock.recv_multipart()
            rid = decode(body).id
            actions = np.zeros((INFO.horizon, INFO.action_dim), np.float32)
            sock.send_multipart([robot, pack_header({
                "v": 1, "kind": "reply", "id": rid, "model": "toy-a", "timings": timings,
                "actions": {"dtype": "float32", "shape": list(actions.shape), "data": actions.tobytes()}})])

    t = threading.Thread(target=loop, daemon=True)
    t.start()
    rt.peers.append(t)


@pytest.mark.parametrize("case", ["long request id", "huge header", "duplicate id"])
def test_a_request_the_router_could_not_attribute_fails_at_once(tmp_path, case):
    """The router can only answer these with id "" (docs/protocol.md); the SDK must not wait for an answer
    it cannot match, nor hand back a stray completion with id ""."""
    images, state = observation()
    with RouterThread(tmp_path, one_executor_table()) as rt:
        rt.answering_executor(b"ex0")
        with RobotClient(rt.cfg.router.bind, robot_id="arm", timeout_s=3.0, context=rt.ctx) as c:
            first = c.submit("toy-a", images, state, request_id="dup") if case == "duplicate id" else None
            t0 = time.monotonic()
            with pytest.raises(RobionError) as e:
                if case == "huge header":
                    c.infer("toy-a", images, state, instruction="pick " * 20_000)
                else:
                    c.submit("toy-a", images, state, request_id="x" * 300 if case == "long request id" else "dup")
            assert time.monotonic() - t0 < 1.0
            assert not isinstance(e.value, RequestTimeout), e.value
            expected = ErrorCode.TOO_LARGE if case == "huge header" else ErrorCode.BAD_REQUEST
            assert e.value.code == expected, e.value
            got = c.poll(1.0) + c.poll(0.3)
            if first is None:
                assert got == [] and c.pending() == 0
            else:  # the first request with that id is unaffected and gets its own reply
                assert [(x.request_id, x.ok) for x in got] == [("dup", True)] and c.pending() == 0
            assert c.infer("toy-a", images, state).ok  # and the client keeps working


@pytest.mark.parametrize("robot_id", ["r" * 300, "é" * 200, "r" * 240])
def test_a_robot_id_that_cannot_travel_is_refused_without_leaking_a_socket(robot_id):
    """ZeroMQ refuses identities over 255 bytes; ids longer than 256 characters are refused by the router.
    The client used to raise ZMQError with its socket left open (the context then never terminates), or,
    for ids just under the identity limit, send requests whose every id the router refuses."""
    ctx = zmq.Context()
    with pytest.raises(ValueError, match="robot_id"):
        RobotClient("tcp://127.0.0.1:9", robot_id=robot_id, context=ctx)
    t = threading.Thread(target=ctx.term, daemon=True)
    t.start()
    t.join(5)
    assert not t.is_alive(), "a socket was left open: the context cannot terminate"


def test_a_reply_after_its_timeout_is_not_returned_as_a_new_completion(tmp_path):
    """infer() raised RequestTimeout for a request: its late reply must not show up in poll() later
    (it used to, with model "" and a latency of ~0 s)."""
    images, state = observation()
    with RouterThread(tmp_path, one_executor_table()) as rt:
        rt.answering_executor(b"ex0", hold=2)  # answers only once a second request arrives
        with RobotClient(rt.cfg.router.bind, robot_id="arm", timeout_s=3.0, context=rt.ctx) as c:
            with pytest.raises(RequestTimeout):
                c.infer("toy-a", images, state, timeout_s=0.3)
            rid = c.submit("toy-a", images, state)  # releases both replies
            got = []
            end = time.monotonic() + 3
            while time.monotonic() < end and not got:
                got += c.poll(0.2)
            got += c.poll(0.3)
            assert [comp.request_id for comp in got] == [rid], [(x.request_id, x.model) for x in got]
            assert got[0].ok and got[0].model == "toy-a" and c.pending() == 0


@pytest.mark.parametrize("timings", ["fast", [1, 2], {"queue_ms": None}, {"queue_ms": "x"}])
def test_a_garbled_reply_does_not_crash_the_client(tmp_path, timings):
    """decode() promises ProtocolError on anything malformed; a bad `timings` used to escape as
    AttributeError / TypeError / ValueError out of infer() and poll(). Forwarded by the real router, the
    garbled reply fails its request with INTERNAL at once (it used to be dropped, leaving a 10 s wait)."""
    images, state = observation()
    with RouterThread(tmp_path, one_executor_table()) as rt:
        garbling_executor(rt, b"ex0", timings)
        with RobotClient(rt.cfg.router.bind, robot_id="arm", timeout_s=10.0, context=rt.ctx) as c:
            t0 = time.monotonic()
            with pytest.raises(MalformedReply) as e:  # the garbled reply fails its request at once
                c.infer("toy-a", images, state)
            assert time.monotonic() - t0 < 2.0, "infer() waited for its timeout"
            assert e.value.code == ErrorCode.INTERNAL and "timings" in e.value.message, e.value
            rid = c.submit("toy-a", images, state)
            got = c.poll(2.0)
            assert [(x.request_id, x.error.code) for x in got] == [(rid, ErrorCode.INTERNAL)]
            assert c.pending() == 0


def test_submit_does_not_block_forever_while_the_router_is_unreachable(tmp_path):
    """With no router, the DEALER queues up to its high-water mark (1000) and a blocking send then waits
    forever: infer()'s timeout was never reached. Run in a child process, which the test can kill."""
    port, = free_ports(1)
    script = textwrap.dedent(f"""
        import numpy as np
        from shared.client import RobionError, RobotClient
        c = RobotClient("tcp://127.0.0.1:{port}", robot_id="arm", timeout_s=0.2)
        images, state = {{"cam0": np.zeros((8, 8, 3), np.uint8)}}, np.zeros(4, np.float32)
        refused = 0
        for i in range(1100):
            try:
                c.submit("toy-a", images, state)
            except RobionError as exc:
                assert exc.code.value == "UNAVAILABLE", exc
                refused += 1
        try:
            c.infer("toy-a", images, state)
        except RobionError as exc:
            print("infer:", exc.code.value)
        print("refused:", refused, "pending:", c.pending())
        c.close()
    """)
    proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=20)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout.splitlines()
    assert out[0] == "infer: UNAVAILABLE", out
    refused, pending = int(out[1].split()[1]), int(out[1].split()[3])
    # Sends beyond the socket's queue are refused at once, and a refused request is not left pending.
    assert refused > 0 and pending + refused == 1100, out

