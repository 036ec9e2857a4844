"""`robion up` as operators run it: ready message, clean stop on SIGTERM, no orphans even when killed."""

import os
import signal
import subprocess
import sys
import time

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
    line = proc.stdout.readline()
    assert "robion is up" in line, line
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
