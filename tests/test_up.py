"""`robion up` as operators run it: ready message, clean stop on SIGTERM, no orphans even when killed."""

import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from shared.client import RobotClient
from tests.helpers import cluster_config

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def children_of_config(path) -> list[int]:
    """PIDs of live service processes started with this config (zombies excluded)."""
    pids = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            cmd = open(f"/proc/{pid}/cmdline", "rb").read().split(b"\0")
            state = open(f"/proc/{pid}/stat").read().split(") ", 1)[1][0]
        except OSError:
            continue
        if str(path).encode() in cmd and b"services." in b" ".join(cmd) and state != "Z":
            pids.append(int(pid))
    return pids


def start_up(path) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "shared.cli", "up", "-c", str(path)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    lines = [proc.stdout.readline() for _ in range(4)]
    assert lines[0].startswith("starting the cluster from"), lines
    # progress as each executor registers, in either order
    assert {line.split()[1] for line in lines[1:3]} == {"ex0", "ex1"} and "is serving (2 of 2)" in lines[2], lines
    assert "robion is up" in lines[3], lines
    assert len(children_of_config(path)) == 4  # control plane, router, two executors
    return proc


def wait_gone(path, timeout_s: float = 20.0) -> list[int]:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and children_of_config(path):
        time.sleep(0.2)
    return children_of_config(path)


def test_sigterm_stops_everything_cleanly(tmp_path):
    path, _ = cluster_config(tmp_path)
    proc = start_up(path)
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0
    assert "robion stopped" in out and "'router': 0" in out and "'control': 0" in out
    assert wait_gone(path, 1.0) == []


def test_killed_launcher_leaves_no_orphans(tmp_path):
    path, _ = cluster_config(tmp_path)
    proc = start_up(path)
    proc.kill()  # no chance to clean up: the services notice their launcher is gone
    proc.wait(10)
    assert wait_gone(path) == []


def ipv6_loopback_ports(n: int) -> list[int] | None:
    """n free ports on ::1, or None on a host without IPv6 loopback."""
    socks = []
    try:
        for _ in range(n):
            s = socket.socket(socket.AF_INET6)
            socks.append(s)
            s.bind(("::1", 0))
        return [s.getsockname()[1] for s in socks]
    except OSError:
        return None
    finally:
        for s in socks:
            s.close()


def test_a_cluster_on_ipv6_addresses_serves_a_robot(tmp_path):
    """Every service binds and dials IPv6 literals (libzmq refuses them unless a socket turns ZMQ_IPV6 on), and
    a robot's SDK reaches the router at one. The control plane binds the wildcard [::], which peers dial as ::1."""
    ports = ipv6_loopback_ports(3)
    if ports is None:
        pytest.skip("no IPv6 loopback on this host")
    rp, bp, cp = ports
    path, data = cluster_config(tmp_path)
    data["router"].update(bind=f"tcp://[::1]:{rp}", backend=f"tcp://[::1]:{bp}")
    data["control"]["bind"] = f"tcp://[::]:{cp}"
    path.write_text(yaml.safe_dump(data))
    proc = start_up(path)
    try:
        with RobotClient(f"tcp://[::1]:{rp}", robot_id="v6", timeout_s=30) as client:
            info = client.metadata()["toy-a"]
            images = {c: np.zeros(info.image_shape, np.uint8) for c in info.cameras}
            done = client.infer("toy-a", images, np.zeros(info.state_dim, np.float32), "go")
            assert done.actions.shape == (info.horizon, info.action_dim)
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0 and "'router': 0" in out and "'control': 0" in out


def test_two_services_given_one_metrics_port_are_refused_before_anything_starts(tmp_path):
    """ex0's explicit 9111 is ex1's default (9110 + 1): the second to bind only logged a failure, and Prometheus
    scraped ex0 as if it were ex1. `robion up` starts everything on one host, so it refuses such a config."""
    path, data = cluster_config(tmp_path)
    data["executors"][0]["metrics_port"] = 9111
    data["executors"][1].pop("metrics_port", None)
    path.write_text(yaml.safe_dump(data))
    res = subprocess.run([sys.executable, "-m", "shared.cli", "up", "-c", str(path)], cwd=ROOT, capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 1, res.stderr[-800:]
    assert "metrics port 9111 is both executor ex0's and executor ex1's" in res.stderr
    assert children_of_config(path) == []


def test_a_second_cluster_on_the_same_addresses_is_refused_and_the_first_keeps_serving(tmp_path):
    """The second `up` polled the first cluster's control plane, read "ready", said it was up, and its executors
    registered with the first cluster, which had none left once the second was stopped."""
    path, data = cluster_config(tmp_path)
    first = start_up(path)
    try:
        second = tmp_path / "second.yaml"  # the same addresses; another state_dir
        data["control"]["state_dir"] = str(tmp_path / "state2")
        second.write_text(yaml.safe_dump(data))
        res = subprocess.run([sys.executable, "-m", "shared.cli", "up", "-c", str(second)], cwd=ROOT,
                             capture_output=True, text=True, timeout=60)
        assert res.returncode == 1, res.stdout + res.stderr
        assert "cannot bind" in res.stderr and "another cluster" in res.stderr, res.stderr
        assert children_of_config(second) == []
        with RobotClient(data["router"]["bind"], robot_id="after", timeout_s=30) as client:
            info = client.metadata()["toy-a"]
            images = {c: np.zeros(info.image_shape, np.uint8) for c in info.cameras}
            assert client.infer("toy-a", images, np.zeros(info.state_dim, np.float32)).actions is not None
    finally:
        first.send_signal(signal.SIGTERM)
        first.communicate(timeout=60)
    assert first.returncode == 0


def test_up_stops_with_exit_1_when_its_router_dies(tmp_path):
    """It went on waiting for a signal with its router dead, and exited 0 when stopped."""
    path, _ = cluster_config(tmp_path)
    proc = start_up(path)
    router = [pid for pid in children_of_config(path)
              if b"services.router.main" in open(f"/proc/{pid}/cmdline", "rb").read()]
    os.kill(router[0], signal.SIGKILL)
    try:
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1, out
    assert "'router': -9" in out
    assert wait_gone(path) == []


def test_a_second_stop_signal_does_not_cut_the_ordered_stop_short(tmp_path):
    path, data = cluster_config(tmp_path)
    data["fleet"]["duration_s"] = 60
    path.write_text(yaml.safe_dump(data))
    proc = subprocess.Popen([sys.executable, "-m", "shared.cli", "demo", "-c", str(path)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = ""
        while "driving" not in line:
            line = proc.stdout.readline()
            assert line, "the demo ended before its fleet started"
        proc.send_signal(signal.SIGTERM)
        time.sleep(0.3)
        proc.send_signal(signal.SIGTERM)  # while the first stop is under way
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "Traceback" not in err, err
    assert wait_gone(path) == []


def test_demo_refuses_fleet_settings_its_fleet_would_refuse_before_starting_the_cluster(tmp_path):
    """A fleet too short for one period (a report of 0 sent): refused by the fleet, but only once the whole cluster
    had started. Each field's own bounds (hz, robots) are the config's, checked at load."""
    path, data = cluster_config(tmp_path)
    data["fleet"].update(hz=2, duration_s=0.1)
    path.write_text(yaml.safe_dump(data))
    res = subprocess.run([sys.executable, "-m", "shared.cli", "demo", "-c", str(path)], cwd=ROOT,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "robion demo: fleet.duration_s: expected at least one period" in res.stderr, \
        res.stderr
    assert "starting the cluster" not in res.stdout
