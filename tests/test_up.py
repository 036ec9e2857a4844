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
from shared.cluster import control_status
from shared.config import load_config
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


def start_up(path, *extra: str, stderr=subprocess.DEVNULL) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "shared.cli", "up", "-c", str(path), *extra], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=stderr, text=True)
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


def service_pids(path, module: bytes) -> list[int]:
    return [pid for pid in children_of_config(path) if module in open(f"/proc/{pid}/cmdline", "rb").read()]


def test_up_stops_with_exit_1_when_its_router_dies_and_restarts_are_off(tmp_path):
    """It went on waiting for a signal with its router dead, and exited 0 when stopped."""
    path, _ = cluster_config(tmp_path)
    proc = start_up(path, "--max-restarts", "0")
    os.kill(service_pids(path, b"services.router.main")[0], signal.SIGKILL)
    try:
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1, out
    assert "'router': -9" in out
    assert wait_gone(path) == []


def served(address: str, robot: str, model: str = "toy-a", timeout_s: float = 30.0) -> bool:
    with RobotClient(address, robot_id=robot, timeout_s=timeout_s) as client:
        info = client.metadata()[model]
        images = {c: np.zeros(info.image_shape, np.uint8) for c in info.cameras}
        return client.infer(model, images, np.zeros(info.state_dim, np.float32)).actions is not None


def wait_for_new_pid(path, module: bytes, old: int, timeout_s: float = 20.0) -> int:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        pids = [p for p in service_pids(path, module) if p != old]
        if pids:
            return pids[0]
        time.sleep(0.1)
    raise AssertionError(f"{module.decode()} was not started again within {timeout_s} s")


def serving_instance(data: dict, executor: str) -> str | None:
    """The process token of ``executor`` as the control plane has it registered and routed, with the router on that
    table, else None."""
    status = control_status(data["control"]["bind"], timeout_s=1.0) or {}
    entry = status.get("executors", {}).get(executor)
    table = status.get("table", {})
    routed = (any(executor in hosts for hosts in table.get("routes", {}).values())
              and status.get("router", {}).get("version") == table.get("version"))
    return entry.get("instance") if entry and routed else None


def test_up_starts_a_killed_router_and_executor_again_and_robots_are_served(tmp_path):
    """Nothing restarted a failed service: an executor that crashed (or exited 1 after a failed reload, which it does
    for its supervisor) stayed down for the rest of the run, and a dead router stopped the whole cluster."""
    path, data = cluster_config(tmp_path)
    proc = start_up(path, stderr=subprocess.PIPE)
    try:
        router = service_pids(path, b"services.router.main")[0]
        executor = service_pids(path, b"--name\0ex0")[0]
        before = serving_instance(data, "ex0")
        os.kill(router, signal.SIGKILL)
        os.kill(executor, signal.SIGKILL)
        wait_for_new_pid(path, b"services.router.main", router)
        wait_for_new_pid(path, b"--name\0ex0", executor)
        end = time.monotonic() + 60
        while (instance := serving_instance(data, "ex0")) in (None, before) and time.monotonic() < end:
            time.sleep(0.2)
        assert instance not in (None, before), "the restarted ex0 did not register"
        # toy-b is served by ex0 alone: its reply shows the restarted executor back in routing
        assert served(data["router"]["bind"], "after-restart", model="toy-b")
        assert len(children_of_config(path)) == 4
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    assert "robion up: router exited with code -9: starting it again in 1 s (restart 1 of 5 within 300 s)" in err, err
    assert "robion up: executor[ex0] exited with code -9: starting it again in 1 s" in err, err
    assert "robion up: router started again" in err and "robion up: executor[ex0] started again" in err, err
    assert proc.returncode == 1, out  # a service failed during the run, though it was brought back
    assert "'router': 0" in out and "'executor[ex0]': 0" in out, out  # the restarted ones stop cleanly
    assert wait_gone(path) == []


def test_up_leaves_down_an_executor_that_fails_more_often_than_allowed_and_keeps_serving(tmp_path):
    path, data = cluster_config(tmp_path)
    proc = start_up(path, "--max-restarts", "1", stderr=subprocess.PIPE)
    try:
        first = service_pids(path, b"--name\0ex1")[0]
        os.kill(first, signal.SIGKILL)
        second = wait_for_new_pid(path, b"--name\0ex1", first)
        time.sleep(1.0)  # let it get past its imports
        os.kill(second, signal.SIGKILL)
        time.sleep(5.0)  # a second restart would come 2 s after this failure, plus a poll of 0.5 s
        assert service_pids(path, b"--name\0ex1") == []
        assert proc.poll() is None  # the cluster goes on, ex0 serves toy-a
        assert served(data["router"]["bind"], "still-served")
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    assert "executor[ex1] exited with code -9: failure 2 within 300 s, more than the 1 restarts allowed: " \
           "not restarted" in err, err
    assert proc.returncode == 1
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


def test_restart_policy_backs_off_limits_failures_in_its_window_and_skips_clean_and_refused_exits():
    from shared.cluster import RestartPolicy

    policy = RestartPolicy(max_restarts=3, window_s=100.0, backoff_s=(1.0, 5.0))
    assert policy.after_exit("x", 0, 0.0)[0] is None  # a clean stop
    assert policy.after_exit("x", 2, 0.0)[0] is None  # its config or device refused: it would fail again
    assert [policy.after_exit("x", c, t)[0] for c, t in ((1, 0.0), (-9, 10.0), (1, 20.0))] == [1.0, 5.0, 5.0]
    delay, why = policy.after_exit("x", 1, 30.0)
    assert delay is None and "failure 4 within 100 s" in why
    assert policy.after_exit("y", 1, 30.0)[0] == 1.0  # per service
    assert policy.after_exit("x", 1, 115.0)[0] == 5.0  # the failures at 0 and 10 s have left the window
    assert RestartPolicy(max_restarts=0).after_exit("x", 1, 0.0)[0] is None


def test_stop_gives_an_executor_the_time_its_drain_can_take(tmp_path):
    """An executor's stop waits for the control plane's solve (up to 20 s) before its last answers; `robion up` killed
    it after 10 s. A stand-in that takes 11 s to stop after SIGTERM is let finish; a router that slow is not."""
    from shared.cluster import LocalCluster

    path, _ = cluster_config(tmp_path)
    slow = ("import signal, sys, time\n"
            "signal.signal(signal.SIGTERM, lambda *_: (time.sleep(11), sys.exit(0)))\n"
            "print('ready', flush=True)\n"
            "time.sleep(120)\n")
    cluster = LocalCluster(load_config(path), path)
    for name in ("executor[ex0]", "router"):
        cluster.procs[name] = subprocess.Popen([sys.executable, "-c", slow], stdout=subprocess.PIPE, text=True)
        assert cluster.procs[name].stdout.readline() == "ready\n"
    codes = cluster.stop(grace_s=1.0)
    assert codes == {"executor[ex0]": 0, "router": -9}
