"""An executor that goes silent without closing its connection: a frozen process (SIGSTOP, a paused container) or a
host that lost power or its network. The OS closes nothing, so only the ZMTP heartbeats of shared.service.keep_alive
tell the router; it then fails the executor's requests in flight as it does a crashed one's, instead of leaving them
to router.request_timeout_s, and the model's other executors take the traffic.

The first tests freeze a TCP proxy between the router (its real loop in a thread) and a stand-in executor, with
short heartbeats (router.keepalive_s), or between a real executor's I/O loop and a stand-in router, which the
executor must redial (a router whose host died and came back). Another stops a real executor process of a real
cluster, the control plane killed first (with the plane up, its own heartbeats find the frozen executor within
control.heartbeat_s x missed_heartbeats). The last ones take an executor's name from it, at the router or the
control plane, as a second process of that name would."""

from __future__ import annotations

import signal
import time

import numpy as np
import pytest
import zmq

from shared.client import RobionError, RobotClient
from shared.cluster import LocalCluster, control_status
from shared.config import load_config
from shared.protocol import ErrorCode, ErrorReply, decode
from tests.helpers import cluster_config, free_ports, wait_for
from tests.test_executor_io import Harness
from tests.test_executor_reconnect import hellos_until, restart_router, said
from tests.test_router_restart import LONG_TIMEOUT_S, ResettingProxy, executor_behind_proxy, held_request
from tests.test_router_robustness import RouterThread, one_executor_table


def served_again(client: RobotClient, model: str, images: dict, state: np.ndarray) -> bool:
    """Whether three requests in a row are served; False on UNAVAILABLE (the executor has not redialled yet)."""
    try:
        return all(client.infer(model, images, state).ok for _ in range(3))
    except RobionError as exc:
        assert exc.code == ErrorCode.UNAVAILABLE, exc
        return False


def test_a_frozen_connection_is_failed_after_the_heartbeat_timeout(tmp_path):
    """The proxy stops passing bytes both ways and closes nothing: the router's pings go unanswered, so it closes the
    connection after router.keepalive_s and answers the request UNAVAILABLE, long before request_timeout_s."""
    with RouterThread(tmp_path, one_executor_table(), request_timeout_s=LONG_TIMEOUT_S, keepalive_s=0.6) as rt:
        proxy, ex = executor_behind_proxy(rt)
        try:
            robot = rt.robot(b"arm")
            held_request(rt, robot, ex, "r1")
            time.sleep(1.0)  # several heartbeat intervals: a connection that passes bytes is kept
            assert rt.router.in_flight, "a live connection was failed"
            t0 = time.monotonic()
            proxy.freeze()
            assert robot.poll(20_000), "no answer within 20 s of the freeze"
            took = time.monotonic() - t0
            rep = decode(robot.recv_multipart())
            assert isinstance(rep, ErrorReply) and rep.code == ErrorCode.UNAVAILABLE, rep
            assert "closed its connection" in rep.message, rep.message
            assert took < 10.0, took  # timeout 0.6 s + grace 0.5 s, with room for a loaded host; before: 60 s
        finally:
            proxy.close()


def test_keepalive_0_turns_the_heartbeats_off(tmp_path):
    """router.keepalive_s: 0 (for links where a request takes longer to cross than any timeout): a frozen connection
    stays up, and its request waits for request_timeout_s as before the heartbeats."""
    with RouterThread(tmp_path, one_executor_table(), request_timeout_s=LONG_TIMEOUT_S, keepalive_s=0) as rt:
        proxy, ex = executor_behind_proxy(rt)
        try:
            robot = rt.robot(b"arm")
            held_request(rt, robot, ex, "r1")
            proxy.freeze()
            assert not robot.poll(3000), decode(robot.recv_multipart())
            assert rt.router.in_flight
        finally:
            proxy.close()


def test_the_executor_redials_a_router_that_went_silent(tmp_path):
    """The connection to the router freezes: the executor's pings go unanswered, so it closes the connection and
    redials (through the proxy, whose new connections pass bytes), says hello again and serves through it. Before,
    it kept the frozen connection for good: a router whose host died and came back never heard from it again."""
    rp, bp, pp = free_ports(3)
    proxy = ResettingProxy(bp)  # listens on a port of its own; the executor dials it, not the router's backend
    router = {"bind": f"tcp://127.0.0.1:{rp}", "backend": f"tcp://127.0.0.1:{bp}",
              "backend_connect": f"tcp://127.0.0.1:{proxy.port}", "max_message_bytes": 1_000_000, "metrics_port": 0,
              "keepalive_s": 0.6}
    h = Harness(tmp_path, router=router)
    try:
        h.router.setsockopt(zmq.ROUTER_HANDOVER, 1)  # as the real router: a redial takes the name over
        hellos_until(h.router, time.monotonic() + 0.5)  # the start-up hellos
        proxy.freeze()
        # (the hellos of every heartbeat carry the first connection's number, 1)
        expected = {"kind": "executor_hello", "executor": "ex0", "instance": h.io.instance, "connection": 2}
        got = hellos_until(h.router, time.monotonic() + 10.0, stop_at=expected)
        assert said(got, expected), f"no hello on a new connection within 10 s: {got}"
        h.send(h.request("after-redial"))
        assert h.router.poll(10_000), "no reply on the new connection"
    finally:
        h.close()
        proxy.close()


def test_a_stopped_executor_process_is_routed_around_with_the_control_plane_down(tmp_path):
    """SIGSTOP one of toy-a's two executors, the control plane killed: its requests are answered UNAVAILABLE within
    seconds (before: request_timeout_s, 30 s), the rest of toy-a's traffic goes to the other executor, and after
    SIGCONT the stopped one reconnects and serves again."""
    path, _ = cluster_config(tmp_path)
    cfg = load_config(path)
    with LocalCluster(cfg, path, log_level="WARNING") as cluster:
        with RobotClient(cfg.router.bind, robot_id="arm", timeout_s=60) as client:
            info = client.metadata()["toy-a"]
            rng = np.random.default_rng(0)
            images = {cam: rng.integers(0, 256, info.image_shape, dtype=np.uint8) for cam in info.cameras}
            state = rng.standard_normal(info.state_dim).astype(np.float32)
            assert all(client.infer("toy-a", images, state).ok for _ in range(4))  # both executors serve
            cluster.procs["control"].kill()
            cluster.procs["control"].wait()
            frozen = cluster.procs["executor[ex1]"]
            frozen.send_signal(signal.SIGSTOP)
            try:
                t0 = time.monotonic()
                ids = [client.submit("toy-a", images, state) for _ in range(10)]  # round-robin: half to ex1
                done = {}
                while len(done) < len(ids) and time.monotonic() - t0 < 40:
                    for comp in client.poll(0.5):
                        done[comp.request_id] = (comp, time.monotonic() - t0)
                assert set(done) == set(ids)
                failed = [(c, t) for c, t in done.values() if not c.ok]
                assert failed, "no request went to the stopped executor"
                for comp, took in failed:
                    assert comp.error.code == ErrorCode.UNAVAILABLE and "ex1" in comp.error.message, comp.error
                    assert took < 12.0, took  # heartbeat 1 s + timeout 3 s + grace 0.5 s, on a loaded host
                # New requests go to ex0 (ex1's identity is unreachable now) and are served.
                assert all(client.infer("toy-a", images, state).ok for _ in range(6))
            finally:
                frozen.send_signal(signal.SIGCONT)
            # ex1 redials, and its late answers to the failed requests are dropped. With ex0 killed too, toy-a is
            # served by ex1 alone.
            cluster.procs["executor[ex0]"].kill()
            assert wait_for(lambda: served_again(client, "toy-a", images, state), 20, 0.2), \
                "the resumed executor did not serve again"
            assert frozen.poll() is None


@pytest.mark.parametrize("taken_at", ["router", "control plane"])
def test_an_executor_gets_its_name_back_from_a_connection_that_took_it(tmp_path, taken_at):
    """A peer connects under an executor's name, to the router's backend or to the control plane (a second process
    started with the same --name by mistake, or a stray client), then leaves. ROUTER_HANDOVER gives it the name and
    detaches the executor's connection without closing it, so the executor saw no disconnect: the router could no
    longer reach it (toy-b, served by ex0 alone, answered UNAVAILABLE for good) and the control plane heard none of
    its heartbeats and dropped it from routing for good. Its heartbeats now find the dead connections and it redials."""
    path, _ = cluster_config(tmp_path)
    cfg = load_config(path)
    with LocalCluster(cfg, path, log_level="WARNING"), RobotClient(cfg.router.bind, robot_id="arm", timeout_s=10) as client:
        info = client.metadata()["toy-b"]
        images = {cam: np.zeros(info.image_shape, np.uint8) for cam in info.cameras}
        state = np.zeros(info.state_dim, np.float32)
        assert client.infer("toy-b", images, state).ok
        ctx = zmq.Context.instance()
        impostor = ctx.socket(zmq.DEALER)
        impostor.setsockopt(zmq.IDENTITY, b"ex0")
        impostor.setsockopt(zmq.LINGER, 0)
        impostor.connect(cfg.router.backend if taken_at == "router" else cfg.control.bind)
        impostor.send(b"")  # a one-frame message both ignore; its handshake takes the name over
        time.sleep(0.5)
        impostor.close()
        time.sleep(2 * cfg.control.heartbeat_s * cfg.control.missed_heartbeats)  # the plane drops an executor it lost
        assert wait_for(lambda: served_again(client, "toy-b", images, state), 20, 0.2), \
            "toy-b's only executor was never reached again"
        assert "ex0" in control_status(cfg.control.bind)["table"]["routes"]["toy-b"]


def test_no_hellos_queue_while_the_router_is_away(tmp_path):
    """The executor says hello each heartbeat only while connected. Queued during an outage, those hellos reached the
    restarted router ahead of the reconnect's, under the old connection's number, and the reconnect then looked like
    one from a connection that router knew (its requests in flight were marked as possibly lost)."""
    h = Harness(tmp_path)
    try:
        hellos_until(h.router, time.monotonic() + 0.5)
        restart_router(h, away_s=8 * h.cfg.control.heartbeat_s)  # away for several heartbeats
        got = hellos_until(h.router, time.monotonic() + 3.0, stop_at={"connection": 2})
        assert got and got[0].get("connection") == 2, got  # the reconnect's hello first: none queued before it
    finally:
        h.close()
