"""Shared test fixtures: free loopback ports, small cluster configs, a control plane in a thread, and
edited copies of wire messages."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import yaml


ROOT = Path(__file__).resolve().parent.parent


def executor_exit(path: Path, *args: str, env: dict | None = None, timeout_s: float = 120) -> subprocess.CompletedProcess:
    """Run the executor process (``--name ex0`` of the config at ``path``, then ``args``) until it exits, as
    one that refuses its start-up does; its stderr is captured."""
    return subprocess.run([sys.executable, "-m", "services.executor.main", "-c", str(path), "--name", "ex0", *args],
                          capture_output=True, text=True, cwd=ROOT, env=env, timeout=timeout_s)


def sigterm_after_line(proc: subprocess.Popen, stream, marker: str, delay_s: float) -> None:
    """Read ``stream`` (a pipe of ``proc``) up to a line holding ``marker``, wait ``delay_s``, then stop the
    process as a supervisor does (SIGTERM)."""
    import signal

    for line in stream:
        if marker in line:
            break
    time.sleep(delay_s)
    proc.send_signal(signal.SIGTERM)


def changed(message: dict, changes: dict) -> dict:
    """A copy of ``message`` with ``changes`` applied; a change of None removes the field."""
    out = dict(message)
    for key, value in changes.items():
        if value is None:
            out.pop(key)
        else:
            out[key] = value
    return out


def free_ports(n: int) -> list[int]:
    socks = []
    for _ in range(n):
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        socks.append(s)
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def wait_until_bindable(address: str, timeout_s: float = 10.0) -> None:
    """Wait until a ``tcp://host:port`` address can be bound again. ZeroMQ closes a socket's listener in
    its I/O thread, after ``close()`` has returned, so a test that binds the address again at once (a
    restarted service) fails now and then with "Address already in use"."""
    host, _, port = address.removeprefix("tcp://").rpartition(":")
    end = time.monotonic() + timeout_s
    while True:
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as ZeroMQ binds: TIME_WAIT is no obstacle
        try:
            s.bind((host, int(port)))
            return
        except OSError:
            if time.monotonic() >= end:
                raise
            time.sleep(0.01)
        finally:
            s.close()


def cluster_config(tmp_path: Path, **overrides) -> tuple[Path, dict]:
    rp, bp, cp = free_ports(3)
    data = {
        "models": [{"name": "toy-a", "arch": "toy", "size": "tiny", "seed": 0, "slo_ms": 500},
                   {"name": "toy-b", "arch": "toy", "size": "tiny", "seed": 1, "slo_ms": 500}],
        "executors": [{"name": "ex0", "device": "cpu", "models": ["toy-a", "toy-b"], "metrics_port": 0},
                      {"name": "ex1", "device": "cpu", "models": ["toy-a"], "metrics_port": 0}],
        "engine": {"kind": "monolithic", "max_batch": 2},
        "router": {"bind": f"tcp://127.0.0.1:{rp}", "backend": f"tcp://127.0.0.1:{bp}",
                   "max_message_bytes": 1_000_000, "metrics_port": 0},
        "control": {"bind": f"tcp://127.0.0.1:{cp}", "heartbeat_s": 0.2, "missed_heartbeats": 5,
                    "state_dir": str(tmp_path / "state"), "metrics_port": 0},
        "fleet": {"robots": 4, "hz": 2, "duration_s": 3},
    }
    data.update(overrides)
    for ex in data["executors"]:  # no fixed ports in tests: parallel runs must not collide
        ex.setdefault("metrics_port", 0)
    path = tmp_path / "cluster.yaml"
    path.write_text(yaml.safe_dump(data))
    return path, data


# The model description a stand-in executor registers (what a real one sends for a tiny toy model).
TOY_INFO = {"cameras": ["cam0"], "image_shape": [8, 8, 3], "state_dim": 4, "horizon": 2, "action_dim": 2,
            "deadline_ms": 500.0, "arch": "toy"}


def start_control_plane(path: Path, data: dict):
    """A real control plane for the config ``data`` (written to ``path``) on its loopback socket, in a
    thread. Stand-in executors send no heartbeats, so they are kept alive for the whole test.
    Returns (config, stop event, thread)."""
    from services.controlplane.server import ControlPlane
    from shared.config import load_config

    data["control"]["missed_heartbeats"] = 500
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    wait_until_bindable(cfg.control.bind)  # a control plane stopped just before may still hold it
    stop = threading.Event()
    t = threading.Thread(target=ControlPlane(cfg).run, args=(stop,), daemon=True)
    t.start()
    return cfg, stop, t


def wait_for(predicate, timeout_s: float, poll_s: float = 0.1):
    """``predicate()``'s first truthy value within ``timeout_s``, checked every ``poll_s``; None when none came."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(poll_s)
    return None


def bound_router(ctx, address: str):
    """A ROUTER socket (no linger) bound at ``address``: a stand-in for the router or control plane an executor dials."""
    import zmq

    sock = ctx.socket(zmq.ROUTER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.bind(address)
    return sock
