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
        assert reply is not None and reply["kind"] == "ok" and reply["unrouted"] == [], reply
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
        # Draining the last host of a model says so (`robion ctl drain` warns): nothing did.
        assert control_request(address, "drain", timeout_s=WAIT_S, executor="ex0")["unrouted"] == []
        assert control_request(address, "drain", timeout_s=WAIT_S, executor="ex1")["unrouted"] == ["toy-a"]
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


def test_an_executor_that_leaves_and_comes_back_is_routed_again(tmp_path):
    """An executor that shuts down withdraws itself first (ExecutorIO.withdraw: `drain`, wait, then
    `deregister`). That drain is its own, for leaving: the next process under its name (a restart, a
    supervisor's after exit 1) must be routed again. It was kept as an operator's drain, by name, so every
    executor that restarted while the control plane ran came back drained for good."""
    import torch
    import zmq

    from services.executor.hosting import EngineSlot, ModelStore
    from services.executor.transport import ExecutorIO
    from shared.metrics import ExecutorMetrics
    from tests.helpers import start_control_plane

    path, data = cluster_config(tmp_path)  # ex0: toy-a, toy-b; ex1: toy-a
    cfg, cp_stop, cp_thread = start_control_plane(path, data)
    address = cfg.control.bind
    ctx = zmq.Context()
    store = ModelStore(torch.device("cpu"))
    try:
        register(address, "ex0", "a")

        def serve_ex1() -> tuple[ExecutorIO, EngineSlot, threading.Event, threading.Thread]:
            # The real I/O layer; no engine is needed to register, withdraw and leave.
            hosted = store.load([cfg.model("toy-a")])
            slot = EngineSlot(cfg.engine, torch.device("cpu"), lambda results: None)
            io = ExecutorIO("ex1", cfg, "cpu", store, slot, hosted,
                            ExecutorMetrics("ex1", "cpu", {n: s.slo_s for n, s in hosted.inputs.items()}), context=ctx)
            stop = threading.Event()
            thread = threading.Thread(target=io.run, args=(stop,), daemon=True)
            thread.start()
            return io, slot, stop, thread

        def routes() -> list[str]:
            status = control_status(address, WAIT_S)
            return status["table"]["routes"].get("toy-a") if status else None

        io, slot, stop, thread = serve_ex1()
        assert wait_for(lambda: routes() == ["ex0", "ex1"], 10), routes()
        # ex1 shuts down as services/executor/main.py does: stop serving, withdraw, close (deregister).
        stop.set()
        thread.join(10)
        io.withdraw(ack_timeout_s=0.5, answer_timeout_s=0.2)
        io.close()
        slot.stop()
        assert wait_for(lambda: "ex1" not in (control_status(address, WAIT_S) or {"executors": {"ex1": 0}})["executors"],
                        10)
        # A new ex1 process starts and registers.
        io, slot, stop, thread = serve_ex1()
        try:
            assert wait_for(lambda: "ex1" in (control_status(address, WAIT_S) or {"executors": {}})["executors"], 10)
            assert wait_for(lambda: routes() == ["ex0", "ex1"], 5), routes()
            assert not control_status(address, WAIT_S)["executors"]["ex1"]["draining"]
        finally:
            stop.set()
            thread.join(10)
            io.close()
            slot.stop()
    finally:
        cp_stop.set()
        cp_thread.join(10)
        ctx.term()


def test_an_executor_killed_after_its_own_drain_is_routed_again_when_it_restarts(tmp_path):
    """An executor killed during withdraw (after its own drain, before its deregister: SIGKILL at the end of
    a container's stop grace period) leaves its drained registry entry behind until its heartbeats time out.
    A new process of that name registering before then is another process: its own drain ended with the old
    one. register kept the old entry's drain, so the new process was never routed and `resume` (an
    operator's) could not lift it."""
    import zmq

    from shared import control
    from tests.helpers import start_control_plane

    path, data = cluster_config(tmp_path)
    cfg, cp_stop, cp_thread = start_control_plane(path, data)  # heartbeats time out only after 100 s
    address = cfg.control.bind
    ctx = zmq.Context()
    try:
        register(address, "ex0", "a")
        register(address, "ex1", "old")
        # The old ex1 drains itself from its own control socket (identity = its name), then is killed.
        sock = ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.IDENTITY, b"ex1")
        sock.connect(address)
        sock.send(control.pack("drain", executor="ex1"))
        assert sock.poll(int(WAIT_S * 1000)) and control.unpack(sock.recv())["kind"] == "ok"
        sock.close(0)
        assert control_status(address, WAIT_S)["executors"]["ex1"]["draining"]
        # The new ex1 process registers before the old entry's heartbeats time out.
        register(address, "ex1", "new")
        status = control_status(address, WAIT_S)
        assert not status["executors"]["ex1"]["draining"], status["executors"]
        assert status["table"]["routes"]["toy-a"] == ["ex0", "ex1"], status["table"]["routes"]
    finally:
        cp_stop.set()
        cp_thread.join(10)
        ctx.term()


def test_status_names_executors_that_serve_other_than_the_desired_state(tmp_path):
    """After a restart the plane knows only its file: status read `ready` while executors served an earlier apply's
    models or settings, and nothing showed the difference."""
    from services.controlplane.server import ControlPlane
    from shared.config import settings_digest

    path, data = cluster_config(tmp_path)  # ex0 hosts toy-a and toy-b, ex1 toy-a
    cfg = load_config(path)
    stop = threading.Event()
    t = threading.Thread(target=ControlPlane(cfg).run, args=(stop,), daemon=True)
    t.start()
    try:
        digest = settings_digest(cfg.model("toy-a"))
        reply = control_request(cfg.control.bind, "register", timeout_s=WAIT_S, executor="ex0", device="cpu",
                                instance="i0", models={"toy-a": TOY_INFO}, settings={"toy-a": digest})
        assert reply is not None and reply["kind"] == "registered", reply
        reply = control_request(cfg.control.bind, "register", timeout_s=WAIT_S, executor="ex1", device="cpu",
                                instance="i1", models={"toy-a": TOY_INFO}, settings={"toy-a": "another"})
        assert reply is not None and reply["kind"] == "registered", reply
        status = control_status(cfg.control.bind, WAIT_S)
        assert status["drift"] == {
            "ex0": {"serves": ["toy-a"], "desired": ["toy-a", "toy-b"], "settings_differ": []},
            "ex1": {"serves": ["toy-a"], "desired": ["toy-a"], "settings_differ": ["toy-a"]}}, status["drift"]
    finally:
        stop.set()
        t.join(10)
