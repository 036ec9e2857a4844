"""The fleet driver refuses bad settings and an empty cluster with a clear error, not a traceback.

A real control plane and router run on loopback sockets in threads; no executor has registered,
so the router answers hello with no models.
"""

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

import services.controlplane.server as server
from services.fleet.robots import run_fleet
from services.router.frontend import Router
from shared.cluster import control_status
from shared.config import load_config
from tests.helpers import cluster_config

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def empty_cluster(tmp_path_factory):
    path, _ = cluster_config(tmp_path_factory.mktemp("fleet"))
    cfg = load_config(path)
    stop = threading.Event()
    threads = [threading.Thread(target=svc.run, args=(stop,), daemon=True)
               for svc in (server.ControlPlane(cfg), Router(cfg))]
    for t in threads:
        t.start()
    end = time.monotonic() + 10
    while time.monotonic() < end and (control_status(cfg.control.bind, 0.5) or {}).get("router", {}).get("version", -1) < 0:
        time.sleep(0.05)
    yield path, cfg
    stop.set()
    for t in threads:
        t.join(10)


def fleet(path, *args):
    return subprocess.run([sys.executable, "-m", "services.fleet.main", "-c", str(path), *args], capture_output=True,
                          text=True, cwd=ROOT, timeout=30)


def test_a_router_serving_no_models_is_reported(empty_cluster):
    path, cfg = empty_cluster
    with pytest.raises(ValueError, match="serves no models"):
        run_fleet(cfg.router.bind, robots=2, hz=2, duration_s=0.5)
    res = fleet(path, "--duration", "0.5")
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    assert "serves no models" in res.stderr


@pytest.mark.parametrize("args, field", [(("--hz", "-1"), "--hz"), (("--hz", "0"), "--hz"),
                                         (("--robots", "0"), "--robots"), (("--duration", "-2"), "--duration"),
                                         (("--network", "carrier-pigeon"), "--network"),
                                         (("--hz", "1e12"), "--hz"),  # a period below the clock's resolution: a hang
                                         (("--hz", "2", "--duration", "0.1"), "--duration")])  # no robot would send
def test_bad_settings_are_refused_before_any_robot_starts(empty_cluster, args, field):
    path, cfg = empty_cluster
    res = fleet(path, *args)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert field in res.stderr, res.stderr


@pytest.mark.parametrize("kwargs, match", [({"hz": -1.0}, "hz"), ({"robots": -3}, "robots"),
                                           ({"duration_s": float("nan")}, "duration"), ({"network": "nope"}, "network")])
def test_run_fleet_validates_its_arguments(empty_cluster, kwargs, match):
    _, cfg = empty_cluster
    settings = {"robots": 2, "hz": 2.0, "duration_s": 0.5, **kwargs}
    with pytest.raises(ValueError, match=match):
        run_fleet(cfg.router.bind, **settings)
