"""Heartbeats that wait in the control plane's socket while it solves do not expire their executors.

The control plane runs the CP-SAT solve in its only thread and reads at most 256 messages a round
before it checks heartbeats. A live executor whose last heartbeat was read before a multi-second
solve, with its later ones still queued behind the round's cap, was expired, told to register again,
and its registration solved again: a storm. A real control plane and real CP-SAT solves run here;
stand-in executors send, over one socket (so the plane reads the messages in exactly this order),
what live executors send.
"""

import threading
import time
import uuid

import yaml
import zmq

from shared import control
from shared.cluster import control_status
from tests.helpers import TOY_INFO, cluster_config

# Limits and populations that CP-SAT does not prove optimal within its time limit, on 7 and on 8 GPUs.
LIMITS = [7, 9, 11, 13, 17, 19, 23, 29]
ROBOTS = [4, 6, 8, 12, 14, 17, 20, 27]
GPUS = [f"g{j}" for j in range(8)]
SOLVE_S = 2.0
HEARTBEAT_S, MISSED = 0.1, 10  # expired after 1 s without a heartbeat


def test_heartbeats_queued_behind_a_long_solve_do_not_expire_live_executors(tmp_path):
    from services.controlplane.server import ControlPlane
    from shared.config import load_config

    models = [{"name": f"m{i}", "arch": "toy", "size": "tiny", "seed": i, "slo_ms": 500, "limit": c, "robots": n}
              for i, (c, n) in enumerate(zip(LIMITS, ROBOTS))]
    names = [m["name"] for m in models]
    path, data = cluster_config(tmp_path, models=models,
                                executors=[{"name": g, "device": "cpu", "models": names} for g in GPUS])
    data["control"].update(heartbeat_s=HEARTBEAT_S, missed_heartbeats=MISSED, solve_time_limit_s=SOLVE_S)
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    stop = threading.Event()
    t = threading.Thread(target=ControlPlane(cfg).run, args=(stop,), daemon=True)
    t.start()

    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(cfg.control.bind)
    replies: list[dict] = []

    def send(kind: str, **fields) -> None:
        sock.send(control.pack(kind, **fields))

    def beat() -> None:
        for g in GPUS:
            send("heartbeat", executor=g, depths={})

    def collect() -> None:
        while sock.poll(0):
            replies.append(control.unpack(sock.recv()))

    def live_for(seconds: float) -> None:
        """Heartbeat every executor as a live one does, and keep what the plane answers."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            beat()
            collect()
            time.sleep(HEARTBEAT_S / 2)

    def wait_reply(kind: str, count: int, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while sum(r["kind"] == kind for r in replies) < count and time.monotonic() < end:
            live_for(HEARTBEAT_S)
        assert sum(r["kind"] == kind for r in replies) >= count, replies

    try:
        for g in GPUS:
            send("register", executor=g, device="cpu", instance=uuid.uuid4().hex, models={m: TOY_INFO for m in names})
        beat()  # read after the registrations' solves, as a live executor's would be
        wait_reply("registered", len(GPUS), 30)
        send("drain", executor="g7")  # 7 GPUs: a solve of SOLVE_S
        wait_reply("ok", 1, 30)
        live_for(0.5)
        assert not any(r["kind"] == "reregister" for r in replies), replies
        replies.clear()

        # The round: message 1 starts a solve (resume: 8 GPUs); meanwhile the executors beat once, and
        # 246 messages that need no work (a deregister of a name never registered) and another
        # solve-starting message (drain) queue behind, the last one the round's 256th.
        send("resume", executor="g7")
        time.sleep(SOLVE_S / 4)  # the plane is solving now
        beat()
        for _ in range(246):
            send("deregister", executor="nobody")
        send("drain", executor="g7")
        # The executors stay alive throughout: their heartbeats queue while the plane solves again.
        live_for(SOLVE_S * 2 + 1.5)
        assert sum(r["kind"] == "ok" for r in replies) == 2, replies  # both solves ran
        told = [r for r in replies if r["kind"] == "reregister"]
        assert not told, f"live executors were expired and told to register again {len(told)} times"
        # Executors that do stop beating are still expired once the plane has caught up.
        end = time.monotonic() + 20
        while (status := control_status(cfg.control.bind, 10)) is not None and status["executors"] \
                and time.monotonic() < end:
            time.sleep(0.2)
        assert status is not None and status["executors"] == {}, status
        assert t.is_alive()
    finally:
        sock.close(0)
        stop.set()
        t.join(30)


def test_a_new_process_registers_while_a_stale_connection_holds_its_name(tmp_path):
    """Executors connect to the control plane with their name as socket identity. While an old connection of
    that name stays open (a hung process, a half-open TCP connection left by a crashed host), libzmq ignored the
    new process's connection for its whole life: its register went unanswered and it never rejoined routing."""
    import threading

    import zmq

    from services.controlplane.server import ControlPlane
    from shared import control
    from shared.cluster import control_status
    from shared.config import load_config
    from tests.helpers import TOY_INFO, cluster_config, wait_for

    path, data = cluster_config(tmp_path)
    data["control"].update(heartbeat_s=0.1, missed_heartbeats=3)
    path.write_text(yaml.safe_dump(data))
    address = load_config(path).control.bind
    stop = threading.Event()
    t = threading.Thread(target=ControlPlane(load_config(path)).run, args=(stop,), daemon=True)
    t.start()
    ctx = zmq.Context()

    def executor_socket() -> zmq.Socket:
        s = ctx.socket(zmq.DEALER)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.IDENTITY, b"ex1")  # as the executor's control socket
        s.connect(address)
        return s

    def register(s: zmq.Socket, instance: str) -> dict | None:
        s.send(control.pack("register", executor="ex1", device="cpu", instance=instance, models={"toy-a": TOY_INFO}))
        return control.unpack(s.recv()) if s.poll(3000) else None

    try:
        old = executor_socket()
        assert (register(old, "old") or {}).get("kind") == "registered"
        # The old process hangs: its connection stays open and silent, and its entry expires.
        assert wait_for(lambda: "ex1" not in control_status(address, 5)["executors"], 10)
        new = executor_socket()
        assert (register(new, "new") or {}).get("kind") == "registered"
        assert "ex1" in control_status(address, 5)["executors"]
    finally:
        stop.set()
        t.join(10)
        ctx.destroy(0)
