"""The router applies the traffic controller's solution by pinning robots to executors."""

import time
import urllib.request

import numpy as np
import yaml

from services.router.routing import Routing
from shared.client import RobotClient
from shared.cluster import LocalCluster, control_status
from shared.config import load_config
from shared.control import RoutingTable
from tests.helpers import cluster_config, free_ports


def table(version=1, quotas=None, limits=None):
    return RoutingTable(version=version, models={}, routes={"A": ["g0", "g1"], "B": ["g0", "g1"]},
                        quotas=quotas or {}, limits=limits or {})


def test_pins_follow_quotas_and_extra_robots_go_to_least_loaded():
    r = Routing()
    r.update(table(quotas={"A": {"g0": 4, "g1": 2}, "B": {"g1": 2}}, limits={"A": 4, "B": 4}))
    picks = {f"a{i}": r.candidates("A", f"a{i}".encode())[0] for i in range(6)}
    picks.update({f"b{i}": r.candidates("B", f"b{i}".encode())[0] for i in range(2)})
    assert sorted(picks[f"a{i}"] for i in range(6)).count("g0") == 4
    assert [picks["b0"], picks["b1"]] == ["g1", "g1"]
    # A robot keeps its executor across requests.
    assert all(r.candidates("A", f"a{i}".encode())[0] == picks[f"a{i}"] for i in range(6))
    # Both GPUs are full (load 1.0 each): an undeclared robot goes to the less loaded, here either; then balance.
    extra = [r.candidates("B", f"x{i}".encode())[0] for i in range(2)]
    assert sorted(extra) == ["g0", "g1"]


def test_new_solve_keeps_pins_that_still_fit():
    """A re-solve moves only the robots it has to: here g1's quota shrinks from 2 to 1, so one of its two
    robots moves to g0 and the other three keep their executors, whatever order they ask in afterwards."""
    r = Routing()
    r.update(table(quotas={"A": {"g0": 2, "g1": 2}}, limits={"A": 4}))
    first = {i: r.candidates("A", str(i).encode())[0] for i in range(4)}
    assert sorted(first.values()) == ["g0", "g0", "g1", "g1"]
    r.update(table(version=2, quotas={"A": {"g0": 3, "g1": 1}}, limits={"A": 4}))
    after = {i: r.candidates("A", str(i).encode())[0] for i in reversed(range(4))}
    moved = [i for i in first if after[i] != first[i]]
    assert len(moved) == 1 and first[moved[0]] == "g1" and after[moved[0]] == "g0", (first, after)
    assert sorted(after.values()) == ["g0", "g0", "g0", "g1"]


def test_a_silent_robot_gives_its_place_in_the_quota_back():
    """A robot that left for good kept its place in its executor's quota until the next solve; the robots
    that came in meanwhile were sent beyond the quotas (to the least-loaded executor, here the one the
    solver gave no A robots)."""
    r = Routing()
    r.update(table(quotas={"A": {"g0": 2}}, limits={"A": 4}))
    assert [r.candidates("A", name, now=0.0)[0] for name in (b"a0", b"a1")] == ["g0", "g0"]
    r.candidates("A", b"a1", now=50.0)  # a1 keeps asking, a0 left
    assert r.release_idle(now=70.0, idle_s=60.0) == 1
    assert r.candidates("A", b"a2", now=70.0)[0] == "g0", "the newcomer did not get a0's place"
    assert r.assigned[("A", "g0")] == 2
    # a0 comes back: g0's places are taken now, so it goes where an extra robot goes.
    assert r.candidates("A", b"a0", now=71.0)[0] == "g1"
    assert r.release_idle(now=100.0, idle_s=60.0) == 0


def test_round_robin_without_assignment():
    r = Routing()
    r.update(table())
    assert [r.candidates("A", b"x")[0] for _ in range(4)] == ["g0", "g1", "g0", "g1"]


def scrape_ok(port: int, model: str) -> float:
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
               if line.startswith("robion_requests_total{") and f'model="{model}"' in line and 'status="ok"' in line)


def test_paper_example_on_a_live_cluster(tmp_path):
    """Models A (6 robots) and B (2 robots), each GPU limited to 4: 4 A on one, 2 A + 2 B on the other."""
    p0, p1 = free_ports(2)
    path, data = cluster_config(tmp_path, executors=[
        {"name": "gpu0", "device": "cpu", "models": ["toy-a", "toy-b"], "metrics_port": p0},
        {"name": "gpu1", "device": "cpu", "models": ["toy-a", "toy-b"], "metrics_port": p1}])
    data["models"][0].update(robots=6, limit=4)
    data["models"][1].update(robots=2, limit=4)
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    with LocalCluster(cfg, path, log_level="WARNING"):
        quotas = control_status(cfg.control.bind)["table"]["quotas"]
        a, b = quotas["toy-a"], quotas["toy-b"]
        full = next(g for g, n in a.items() if n == 4)
        mixed = "gpu1" if full == "gpu0" else "gpu0"
        assert a == {full: 4, mixed: 2} and b == {mixed: 2}
        clients = [(RobotClient(cfg.router.bind, robot_id=f"a{i}"), "toy-a") for i in range(6)]
        clients += [(RobotClient(cfg.router.bind, robot_id=f"b{i}"), "toy-b") for i in range(2)]
        info = clients[0][0].metadata()["toy-a"]
        rng = np.random.default_rng(0)
        images = {c: rng.integers(0, 256, info.image_shape, dtype=np.uint8) for c in info.cameras}
        state = np.zeros(info.state_dim, np.float32)
        for _ in range(3):
            for client, model in clients:
                assert client.infer(model, images, state).ok
        for client, _ in clients:
            client.close()
        port = {"gpu0": p0, "gpu1": p1}
        time.sleep(0.2)
        assert scrape_ok(port[full], "toy-a") == 4 * 3 and scrape_ok(port[full], "toy-b") == 0
        assert scrape_ok(port[mixed], "toy-a") == 2 * 3 and scrape_ok(port[mixed], "toy-b") == 2 * 3
