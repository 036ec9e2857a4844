"""Robot SDK against a real cluster: blocking calls mixed with submit/poll lose no result."""

import time

import numpy as np
import pytest

from shared.client import RobotClient, wait_any
from shared.cluster import LocalCluster
from shared.config import load_config
from tests.helpers import cluster_config


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    path, _ = cluster_config(tmp_path_factory.mktemp("client"),
                             executors=[{"name": "ex0", "device": "cpu", "models": ["toy-a", "toy-b"]}])
    cfg = load_config(path)
    with LocalCluster(cfg, path, log_level="WARNING") as c:
        yield c, cfg


@pytest.fixture
def client(cluster):
    _, cfg = cluster
    with RobotClient(cfg.router.bind, robot_id="sdk-test", timeout_s=10) as c:
        info = c.metadata()["toy-a"]
        rng = np.random.default_rng(0)
        images = {cam: rng.integers(0, 256, info.image_shape, dtype=np.uint8) for cam in info.cameras}
        yield c, images, np.zeros(info.state_dim, np.float32)


def collect(c: RobotClient, n: int, within_s: float) -> dict:
    got = {}
    end = time.monotonic() + within_s
    while len(got) < n and time.monotonic() < end:
        for comp in c.poll(0.2):
            got[comp.request_id] = comp
    return got


def test_poll_returns_results_read_by_ping(client):
    """The reviewer's sequence: 4 submits, replies arrive, ping(), then polling must return all 4."""
    c, images, state = client
    ids = [c.submit("toy-a", images, state) for _ in range(4)]
    time.sleep(0.3)
    c.ping()
    got = collect(c, 4, 10.0)
    assert set(got) == set(ids) and all(comp.ok and comp.actions.shape == (10, 7) for comp in got.values())
    assert c.pending() == 0 and c.poll(0) == []


@pytest.mark.parametrize("blocking", ["ping", "metadata", "infer"])
def test_results_read_by_a_blocking_call_are_pending_until_polled(client, blocking):
    c, images, state = client
    ids = [c.submit("toy-a", images, state) for _ in range(4)]
    calls = {"ping": c.ping, "metadata": lambda: c.metadata(refresh=True),
             "infer": lambda: c.infer("toy-b", images, state)}
    end = time.monotonic() + 10
    while len(c._done) < 4 and time.monotonic() < end:  # repeat until the blocking call has read all 4 replies
        calls[blocking]()
    assert len(c._done) == 4, "the replies never arrived"
    assert c.pending() == 4  # read off the socket, but not yet returned: still pending for the caller
    got = c.poll(0)
    assert sorted(comp.request_id for comp in got) == sorted(ids) and all(comp.ok for comp in got)
    assert c.pending() == 0 and not c._done


def test_wait_any_returns_results_read_by_a_blocking_call_at_once(client):
    c, images, state = client
    ids = [c.submit("toy-a", images, state) for _ in range(2)]
    end = time.monotonic() + 10
    while len(c._done) < 2 and time.monotonic() < end:
        c.ping()
    t = time.monotonic()
    got = wait_any([c], 5.0)  # the socket has nothing new: the stashed results must not wait for it
    assert time.monotonic() - t < 1.0
    assert sorted(comp.request_id for _, comp in got) == sorted(ids)
