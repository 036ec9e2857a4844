"""An operator's `drain` holds until `resume` (docs/operations.md): it survives the executor missing its
heartbeats or restarting, and a placement change of that executor. It used to be lost on either, and
the executor was routed again without anyone resuming it."""

import threading
import time

import yaml

from shared.cluster import LocalCluster, control_request, control_status
from shared.config import load_config
from tests.helpers import TOY_INFO, cluster_config, wait_for
from tests.test_controlplane_rollout import apply_and_wait

WAIT_S = 5.0


def register(address: str, name: str, instance: str) -> None:
    reply = control_request(address, "register", timeout_s=WAIT_S, executor=name, device="cpu", instance=instance,
                            models={"toy-a": TOY_INFO})
    assert reply is not None and reply["kind"] == "registered", reply


def test_a_drain_survives_missed_heartbeats_and_a_restart(tmp_path):
    import zmq

    from services.controlplane.server import ControlPlane
    from shared import control

    path, data = cluster_config(tmp_path)
    data["control"].update(heartbeat_s=0.1, missed_heartbeats=3)
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    address = cfg.control.bind
    stop = threading.Event()
    t = threading.Thread(target=ControlPlane(cfg).run, args=(stop,), daemon=True)
    t.start()
    alive: set[str] = set()  # the stand-in executors that heartbeat now

    def beat() -> None:
        sock = zmq.Context.instance().socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(address)
        while not stop.is_set():
            for name in list(alive):
                sock.send(control.pack("heartbeat", executor=name, depths={}))
            time.sleep(0.03)
        sock.close(0)

    beater = threading.Thread(target=beat, daemon=True)
    beater.start()
    try:
        register(address, "ex0", "a")
        register(address, "ex1", "a")
        alive.update({"ex0", "ex1"})
        reply = control_request(address, "drain", timeout_s=WAIT_S, executor="ex1")
        assert reply is not None and reply["kind"] == "ok", reply
        # ex1 misses its heartbeats (a network blip), then registers again when it is heard from.
        alive.discard("ex1")
        assert wait_for(lambda: "ex1" not in control_status(address, WAIT_S)["executors"], 10)
        register(address, "ex1", "a")
        alive.add("ex1")
        status = control_status(address, WAIT_S)
        assert status["executors"]["ex1"]["draining"] and status["table"]["routes"]["toy-a"] == ["ex0"], status
        # ex1 restarts: its old process leaves, a new one registers under its name.
        assert control_request(address, "deregister", timeout_s=0.3, executor="ex1") is None
        register(address, "ex1", "b")
        status = control_status(address, WAIT_S)
        assert status["executors"]["ex1"]["draining"] and status["table"]["routes"]["toy-a"] == ["ex0"], status
        # Only resume routes to it again.
        reply = control_request(address, "resume", timeout_s=WAIT_S, executor="ex1")
        assert reply is not None and reply["kind"] == "ok", reply
        status = control_status(address, WAIT_S)
        assert not status["executors"]["ex1"]["draining"] and status["table"]["routes"]["toy-a"] == ["ex0", "ex1"]
    finally:
        stop.set()
        t.join(10)
        beater.join(10)


def test_a_placement_change_of_a_drained_executor_leaves_it_drained(tmp_path):
    """ex1 is drained by the operator, then `apply` gives it toy-b: it reloads, and stays out of routing."""
    path, data = cluster_config(tmp_path)  # ex0: toy-a, toy-b; ex1: toy-a
    cfg = load_config(path)
    new = yaml.safe_load(path.read_text())
    new["executors"][1]["models"] = ["toy-a", "toy-b"]
    with LocalCluster(cfg, path, log_level="WARNING"):
        reply = control_request(cfg.control.bind, "drain", timeout_s=10, executor="ex1")
        assert reply is not None and reply["kind"] == "ok", reply
        status = apply_and_wait(cfg.control.bind, new, ["ex1"])
        assert status["rollout"]["done"] == ["ex1"] and status["executors"]["ex1"]["models"] == ["toy-a", "toy-b"]
        assert status["executors"]["ex1"]["draining"], status["executors"]
        assert status["table"]["routes"] == {"toy-a": ["ex0"], "toy-b": ["ex0"]}, status["table"]["routes"]
        reply = control_request(cfg.control.bind, "resume", timeout_s=10, executor="ex1")
        assert reply is not None and reply["kind"] == "ok", reply
        routes = control_status(cfg.control.bind, 5)["table"]["routes"]
        assert routes == {"toy-a": ["ex0", "ex1"], "toy-b": ["ex0", "ex1"]}, routes
