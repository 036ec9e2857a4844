"""Integration: the real router, control plane and executor processes on loopback."""

import time

import numpy as np
import pytest

from shared.client import RobionError, RobotClient, wait_any
from shared.cluster import LocalCluster, control_request, control_status
from shared.config import load_config
from shared.protocol import ErrorCode
from tests.helpers import cluster_config, wait_for


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    path, _ = cluster_config(tmp_path_factory.mktemp("cluster"))
    cfg = load_config(path)
    c = LocalCluster(cfg, path, log_level="WARNING")
    c.start(timeout_s=120)
    yield c, cfg
    c.stop()


def obs(info, rng):
    images = {cam: rng.integers(0, 256, info.image_shape, dtype=np.uint8) for cam in info.cameras}
    return images, rng.standard_normal(info.state_dim).astype(np.float32)


def test_metadata_infer_and_ping(cluster):
    _, cfg = cluster
    with RobotClient(cfg.router.bind, robot_id="arm-1") as client:
        meta = client.metadata()
        assert set(meta) == {"toy-a", "toy-b"}
        info = meta["toy-a"]
        assert (info.horizon, info.action_dim, info.deadline_ms, info.arch) == (10, 7, 500.0, "toy")
        images, state = obs(info, np.random.default_rng(0))
        done = client.infer("toy-a", images, state, "pick up the cup")
        assert done.actions.shape == (10, 7) and done.actions.dtype == np.float32
        assert np.isfinite(done.actions).all()
        t = done.timings
        assert t.server_ms > 0 and t.vlm_ms > 0 and t.action_ms > 0
        assert t.server_ms >= t.queue_ms + t.vlm_ms + t.action_ms - 0.5
        # Camera images may also be passed positionally, in metadata order.
        assert client.infer("toy-b", [images[c] for c in info.cameras], state).actions.shape == (10, 7)
        assert client.ping() < 1.0


def test_error_replies_reach_the_robot(cluster):
    _, cfg = cluster
    with RobotClient(cfg.router.bind, timeout_s=10) as client:
        info = client.metadata()["toy-a"]
        images, state = obs(info, np.random.default_rng(1))
        cases = [
            (("nope", images, state), ErrorCode.UNKNOWN_MODEL),
            (("toy-a", {**images, info.cameras[0]: np.zeros((32, 32, 3), np.uint8)}, state), ErrorCode.SHAPE_MISMATCH),
            (("toy-a", {"left": images[info.cameras[0]], "right": images[info.cameras[1]]}, state), ErrorCode.SHAPE_MISMATCH),
            (("toy-a", images, np.zeros(3, np.float32)), ErrorCode.SHAPE_MISMATCH),
            (("toy-a", {c: i.astype(np.float32) for c, i in images.items()}, state), ErrorCode.SHAPE_MISMATCH),
            (("toy-a", images, np.full(info.state_dim, np.nan, np.float32)), ErrorCode.BAD_REQUEST),
        ]
        for args, code in cases:
            with pytest.raises(RobionError) as e:
                client.infer(*args)
            assert e.value.code == code, e.value
        assert client.infer("toy-a", images, state).ok  # the connection is still good


def test_many_robots_from_one_process(cluster):
    _, cfg = cluster
    clients = [RobotClient(cfg.router.bind, robot_id=f"r{i}") for i in range(16)]
    try:
        info = clients[0].metadata()["toy-a"]
        rng = np.random.default_rng(2)
        ids = {c.submit("toy-a" if i % 2 else "toy-b", *obs(info, rng)) for i, c in enumerate(clients)}
        got = {}
        end = time.monotonic() + 30
        while len(got) < len(ids) and time.monotonic() < end:
            for _, comp in wait_any(clients, 1.0):
                got[comp.request_id] = comp
        assert set(got) == ids and all(c.ok for c in got.values())
    finally:
        for c in clients:
            c.close()


def test_executor_loss_answers_every_request(cluster):
    """Kill one executor mid-traffic: every request still gets exactly one answer, and routing heals."""
    c, cfg = cluster
    client = RobotClient(cfg.router.bind, timeout_s=20)
    info = client.metadata()["toy-a"]
    images, state = obs(info, np.random.default_rng(3))
    ids = [client.submit("toy-a", images, state) for _ in range(40)]
    c.procs["executor[ex1]"].kill()
    got = {}
    end = time.monotonic() + 30
    while len(got) < len(ids) and time.monotonic() < end:
        for comp in client.poll(1.0):
            got[comp.request_id] = comp
    assert set(got) == set(ids)
    assert all(comp.ok or comp.error.code == ErrorCode.UNAVAILABLE for comp in got.values())
    end = time.monotonic() + 10
    while time.monotonic() < end:
        if control_status(cfg.control.bind)["table"]["routes"]["toy-a"] == ["ex0"]:
            break
        time.sleep(0.2)
    assert control_status(cfg.control.bind)["table"]["routes"]["toy-a"] == ["ex0"]
    assert all(client.infer("toy-a", images, state).ok for _ in range(5))
    client.close()


def test_shutdown_is_clean(tmp_path):
    path, _ = cluster_config(tmp_path, executors=[{"name": "ex0", "device": "cpu", "models": ["toy-a", "toy-b"]}])
    c = LocalCluster(load_config(path), path, log_level="WARNING")
    c.start(timeout_s=120)
    codes = c.stop()
    assert codes == {"executor[ex0]": 0, "router": 0, "control": 0}
    assert not any(c.alive().values())


def test_scaled_out_replica_joins_and_leaves(tmp_path):
    """An executor outside the config (a compose replica) registers by name and is routed to."""
    import subprocess
    import sys

    path, _ = cluster_config(tmp_path, executors=[{"name": "ex0", "device": "cpu", "models": ["toy-a", "toy-b"]}])
    cfg = load_config(path)
    with LocalCluster(cfg, path, log_level="WARNING"):
        extra = subprocess.Popen([sys.executable, "-m", "services.executor.main", "-c", str(path), "--name", "replica-9",
                                  "--models", "toy-b", "--metrics-port", "0", "--log-level", "WARNING"])
        try:
            end = time.monotonic() + 60
            while time.monotonic() < end and control_status(cfg.control.bind)["table"]["routes"]["toy-b"] != ["ex0", "replica-9"]:
                time.sleep(0.2)
            assert control_status(cfg.control.bind)["table"]["routes"]["toy-b"] == ["ex0", "replica-9"]
            # With ex0 drained only the replica can answer: the requests show that it is routed to.
            assert control_request(cfg.control.bind, "drain", timeout_s=10, executor="ex0")["kind"] == "ok"
            assert wait_for(lambda: control_status(cfg.control.bind)["ready"], 10)  # the router has the table
            with RobotClient(cfg.router.bind) as client:
                info = client.metadata()["toy-b"]
                images, state = obs(info, np.random.default_rng(5))
                assert all(client.infer("toy-b", images, state).ok for _ in range(6))
            assert control_request(cfg.control.bind, "resume", timeout_s=10, executor="ex0")["kind"] == "ok"
        finally:
            extra.terminate()
            assert extra.wait(30) == 0
        end = time.monotonic() + 10
        while time.monotonic() < end and control_status(cfg.control.bind)["table"]["routes"]["toy-b"] != ["ex0"]:
            time.sleep(0.2)
        assert control_status(cfg.control.bind)["table"]["routes"]["toy-b"] == ["ex0"]
