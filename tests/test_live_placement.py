"""Live placement changes: `robion ctl apply` while robots keep sending; drain and resume."""

import subprocess
import sys
import threading
import time

import numpy as np
import yaml

from shared.client import RobotClient, wait_any
from shared.cluster import LocalCluster, control_status
from shared.config import load_config
from tests.helpers import cluster_config


def drive(address: str, stop: threading.Event, out: dict) -> None:
    """Four robots (two per model) at 20 Hz until stopped; every request must be answered."""
    clients = [(RobotClient(address, robot_id=f"live-{i}"), "toy-a" if i % 2 else "toy-b") for i in range(4)]
    info = clients[0][0].metadata()["toy-a"]
    rng = np.random.default_rng(0)
    images = {c: rng.integers(0, 256, info.image_shape, dtype=np.uint8) for c in info.cameras}
    state = np.zeros(info.state_dim, np.float32)
    sent, done = set(), {}
    next_send = time.monotonic()
    while not stop.is_set():
        if time.monotonic() >= next_send:
            for c, model in clients:
                sent.add(c.submit(model, images, state))
            next_send += 0.05
        for _, comp in wait_any([c for c, _ in clients], 0.01):
            done[comp.request_id] = comp
    end = time.monotonic() + 20
    while len(done) < len(sent) and time.monotonic() < end:
        for _, comp in wait_any([c for c, _ in clients], 0.1):
            done[comp.request_id] = comp
    for c, _ in clients:
        c.close()
    out.update(sent=sent, done=done)


def ctl(path, *args):
    return subprocess.run([sys.executable, "-m", "shared.cli", "ctl", *args, "-c", str(path)], capture_output=True,
                          text=True, timeout=300)


def test_apply_moves_a_model_without_dropping_requests(tmp_path):
    path, data = cluster_config(tmp_path)  # ex0: toy-a, toy-b; ex1: toy-a
    cfg = load_config(path)
    moved = yaml.safe_load(path.read_text())
    moved["executors"][0]["models"] = ["toy-a"]
    moved["executors"][1]["models"] = ["toy-a", "toy-b"]
    new_path = tmp_path / "moved.yaml"
    new_path.write_text(yaml.safe_dump(moved))
    with LocalCluster(cfg, path, log_level="WARNING"):
        stop, out = threading.Event(), {}
        load = threading.Thread(target=drive, args=(cfg.router.bind, stop, out))
        load.start()
        time.sleep(1.0)
        res = ctl(path, "apply", str(new_path))
        assert res.returncode == 0, res.stderr
        assert "executors to reload in turn: ['ex1', 'ex0']" in res.stdout  # the gaining executor goes first
        time.sleep(1.0)
        stop.set()
        load.join(60)
        status = control_status(cfg.control.bind)
        assert status["table"]["routes"] == {"toy-a": ["ex0", "ex1"], "toy-b": ["ex1"]}
        assert status["rollout"]["done"] == ["ex1", "ex0"]
        sent, done = out["sent"], out["done"]
        assert len(sent) > 100 and set(done) == sent
        errors = [c.error for c in done.values() if not c.ok]
        assert errors == [], errors[:5]

        # Drain: ex1 takes nothing new, toy-b has no other host, so it is unavailable; resume brings it back.
        assert ctl(path, "drain", "ex1").returncode == 0
        assert control_status(cfg.control.bind)["table"]["routes"] == {"toy-a": ["ex0"]}
        assert ctl(path, "resume", "ex1").returncode == 0
        assert control_status(cfg.control.bind)["table"]["routes"]["toy-b"] == ["ex1"]
        bad = ctl(path, "drain", "nobody")
        assert bad.returncode == 1 and "no executor named 'nobody'" in bad.stderr
        broken = tmp_path / "broken.yaml"
        broken.write_text(yaml.safe_dump({**moved, "engine": {"max_batch": 3}}))
        res = ctl(path, "apply", str(broken))
        assert res.returncode == 1 and "engine.max_batch: expected a power of two" in res.stderr
        # A valid file whose engine or executor device differs is refused whole: those settings
        # are read at start-up, and status must not claim what the running processes do not do.
        version = control_status(cfg.control.bind)["table"]["version"]
        restart = tmp_path / "restart.yaml"
        engine = {**moved.get("engine", {}), "max_batch": 2 * cfg.engine.max_batch}
        executors = [{**ex, "device": "cuda:7"} if ex["name"] == "ex0" else ex for ex in moved["executors"]]
        restart.write_text(yaml.safe_dump({**moved, "engine": engine, "executors": executors}))
        res = ctl(path, "apply", str(restart))
        assert res.returncode == 1, res.stdout
        assert f"engine.max_batch: {cfg.engine.max_batch} -> {2 * cfg.engine.max_batch}" in res.stderr
        assert "executors.ex0.device: 'cpu' -> 'cuda:7'" in res.stderr and "nothing was changed" in res.stderr
        status = control_status(cfg.control.bind)
        assert status["table"]["version"] == version and status["rollout"]["done"] == ["ex1", "ex0"]
