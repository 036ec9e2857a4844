"""The control plane's admin API answers every `apply`, even one that fails in an unforeseen way."""

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

import services.controlplane.server as server
from shared.cluster import control_request, control_status
from shared.config import load_config
from tests.helpers import cluster_config

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def plane(tmp_path):
    """A real control plane on a loopback socket, in a thread (apply needs no router or executors)."""
    path, data = cluster_config(tmp_path)
    cp = server.ControlPlane(load_config(path))
    stop = threading.Event()
    t = threading.Thread(target=cp.run, args=(stop,), daemon=True)
    t.start()
    yield path, data
    stop.set()
    t.join(10)


def ctl(path, *args):
    return subprocess.run([sys.executable, "-m", "shared.cli", "ctl", *args, "-c", str(path)], capture_output=True,
                          text=True, cwd=ROOT, timeout=60)


def test_apply_of_a_nameless_grouped_model_is_answered(plane, tmp_path):
    path, _ = plane
    bad = tmp_path / "bad.yaml"
    bad.write_text("models:\n  - {arch: toy}\ngpus: 1\nplacement: {groups: {toy: 1}}\n")
    res = ctl(path, "apply", str(bad))
    assert res.returncode == 1, res.stdout
    assert "robion ctl apply: config error: models[0].name: missing" in res.stderr, res.stderr
    assert control_status(load_config(path).control.bind, timeout_s=5) is not None


def test_unexpected_apply_failure_is_answered_and_the_plane_keeps_serving(plane, monkeypatch):
    path, data = plane
    address = load_config(path).control.bind

    def broken(*args, **kwargs):
        raise RuntimeError("planner exploded")

    monkeypatch.setattr(server, "plan_steps", broken)
    reply = control_request(address, "apply", timeout_s=10, config=yaml.safe_dump(data))
    assert reply is not None and reply["kind"] == "error"
    assert "apply failed on the control plane: RuntimeError: planner exploded" in reply["message"]
    monkeypatch.undo()
    assert control_status(address, timeout_s=5)["rollout"] is None  # nothing was half-applied
    reply = control_request(address, "apply", timeout_s=10, config=yaml.safe_dump(data))
    assert reply is not None and reply["kind"] == "applied", reply


def test_failing_periodic_work_does_not_end_the_plane(plane, monkeypatch):
    path, _ = plane
    address = load_config(path).control.bind
    calls = []

    def broken(*args, **kwargs):
        calls.append(1)
        raise RuntimeError("re-plan exploded")

    monkeypatch.setattr(server.ClusterState, "expire", broken)
    deadline = time.monotonic() + 5
    while len(calls) < 3 and time.monotonic() < deadline:  # the loop ticks every 0.1 s
        time.sleep(0.05)
    assert len(calls) >= 3  # it kept ticking after the first failure
    monkeypatch.undo()
    assert control_status(address, timeout_s=5) is not None  # and kept answering


def test_apply_that_a_restarted_control_plane_forgot_is_not_reported_done(tmp_path):
    """`robion ctl apply` waits for its rollout. A control plane restarted meanwhile has no rollout, and the wait
    read that as finished: "placement change done: reloaded []", exit 0, although nothing reloaded (a restarted
    plane applies nothing until an apply of its own). Each rollout has an id now, and the wait checks for its own."""
    from tests.helpers import TOY_INFO, start_control_plane, wait_for

    path, data = cluster_config(tmp_path)  # ex0: toy-a, toy-b; ex1: toy-a
    cfg, stop, t = start_control_plane(path, data)
    address = cfg.control.bind
    for name, models in (("ex0", ["toy-a", "toy-b"]), ("ex1", ["toy-a"])):
        reply = control_request(address, "register", timeout_s=5, executor=name, device="cpu",
                                models={m: TOY_INFO for m in models})
        assert reply is not None and reply["kind"] == "registered", reply
    new = yaml.safe_load(path.read_text())
    new["executors"][1]["models"] = ["toy-a", "toy-b"]
    new_path = tmp_path / "new.yaml"
    new_path.write_text(yaml.safe_dump(new))
    cli = subprocess.Popen([sys.executable, "-m", "shared.cli", "ctl", "apply", str(new_path), "-c", str(path),
                            "--timeout", "60"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        # No router polls this plane, so ex1's step waits drained: the rollout stays pending.
        assert wait_for(lambda: ((control_status(address, 2) or {}).get("rollout") or {}).get("pending") == ["ex1"], 30)
        stop.set()
        t.join(10)
        _, stop, t = start_control_plane(path, data)
        out, err = cli.communicate(timeout=60)
    finally:
        cli.kill()
        stop.set()
        t.join(10)
    assert cli.returncode == 1, out
    assert "placement change done" not in out
    assert "the control plane no longer knows this apply" in err, err
