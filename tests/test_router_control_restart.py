"""A control plane that restarts does not make the router forget the models it serves.

A control plane starts with routing table version 0: no models, no routes, nothing registered. The router
asks for any table whose version differs from its own, so right after a control-plane restart it used to
install that empty table and answer every request UNKNOWN_MODEL ("no model of that name is configured: do
not retry", docs/protocol.md) until an executor registered again, and fail every request in flight. The
real control plane (in a thread) and the real router loop run here; the executor is a DEALER the test drives.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
import zmq

from services.controlplane.state import MAX_AWAITED, ROUTERS_GRACE_S, ClusterState
from services.router.frontend import Router
from shared.cluster import control_request, control_status
from shared.config import dial_address, load_config
from shared.protocol import ErrorReply, InferReply, InferRequest, ModelInfo, decode, encode
from tests.helpers import TOY_INFO, cluster_config, start_control_plane, wait_for


def request(rid: str, model: str = "toy-a") -> list:
    images = {c: np.zeros(TOY_INFO["image_shape"], np.uint8) for c in TOY_INFO["cameras"]}
    return encode(InferRequest(id=rid, robot="arm", model=model, images=images,
                               state=np.zeros(TOY_INFO["state_dim"], np.float32)))


def dealer(ctx: zmq.Context, identity: bytes, address: str) -> zmq.Socket:
    """A stand-in executor (on the router's backend) or robot (on its front end) under ``identity``."""
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.IDENTITY, identity)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(address)
    return sock


def forward_r1(ctx: zmq.Context, cfg, executor: bytes, model: str, socks: list) -> tuple[zmq.Socket, zmq.Socket]:
    """A stand-in ``executor`` says hello to the router, and robot "arm" sends it request r1 for ``model``;
    returns (executor, robot) with r1 in flight at the executor. Both sockets go into ``socks``."""
    ex = dealer(ctx, executor, cfg.router.backend)
    ex.send(b"")
    socks.append(ex)
    arm = dealer(ctx, b"arm", cfg.router.bind)
    socks.append(arm)
    time.sleep(0.2)
    arm.send_multipart(request("r1", model=model))
    assert ex.poll(3000), "not forwarded"
    robot, *body = ex.recv_multipart()
    assert robot == b"arm" and decode(body).id == "r1"
    return ex, arm


@dataclass
class Stack:
    """The real control plane (in a thread, restartable on its address) and the real router loop."""

    path: Path
    data: dict
    ctx: zmq.Context
    router: Router
    address: str
    plane: tuple

    def restart_plane(self) -> None:
        """A new control-plane process on the same address: it starts again from table v0."""
        _, cp_stop, cp_thread = self.plane
        cp_stop.set()
        cp_thread.join(5)
        self.plane = start_control_plane(self.path, self.data)

    def register(self, executor: str, instance: str, models=("toy-a",), timeout_s: float = 5.0) -> dict:
        reply = control_request(self.address, "register", timeout_s=timeout_s, context=self.ctx, executor=executor,
                                device="cpu", instance=instance, models={m: TOY_INFO for m in models})
        assert reply is not None and reply["kind"] == "registered", reply
        return reply

    def routed(self, placement: dict[str, str]) -> None:
        """Register each executor ({name: model}, instance "i" + name) and wait until the router routes by it."""
        for name, model in placement.items():
            self.register(name, "i" + name, models=(model,))
        want: dict[str, list[str]] = {}
        for name, model in placement.items():
            want.setdefault(model, []).append(name)
        assert wait_for(lambda: all(self.router.routing.table.routes.get(m) == e for m, e in want.items()), 5), \
            self.router.routing.table

    def router_polled(self) -> bool:
        """The control plane has heard a table poll from the router."""
        status = control_status(self.address, 1, self.ctx) or {}
        return (status.get("router") or {}).get("last_seen_s") is not None


@contextmanager
def stack(tmp_path, hold: threading.Event | None = None, heartbeat_s: float = 0.2) -> Iterator[Stack]:
    """``hold``, when given, holds the router's loop whenever it is cleared (no table polls meanwhile)."""
    path, data = cluster_config(tmp_path)
    data["control"]["heartbeat_s"] = heartbeat_s
    plane = start_control_plane(path, data)
    cfg = plane[0]
    ctx = zmq.Context()
    router = Router(cfg, ctx)
    if hold is not None:
        expire = router._expire

        def held_expire(now: float) -> None:
            hold.wait(10)
            expire(now)

        router._expire = held_expire
    stop = threading.Event()
    thread = threading.Thread(target=router.run, args=(stop,), daemon=True)
    thread.start()
    st = Stack(path, data, ctx, router, dial_address(cfg.control.bind, cfg.control.connect), plane)
    try:
        yield st
    finally:
        if hold is not None:
            hold.set()
        stop.set()
        thread.join(5)
        _, cp_stop, cp_thread = st.plane
        cp_stop.set()
        cp_thread.join(5)
        ctx.term()


def test_a_restarted_control_planes_empty_table_is_not_installed(tmp_path):
    with stack(tmp_path) as st:
        cfg, ctx, router = st.plane[0], st.ctx, st.router
        socks = []
        try:
            st.register("ex0", "i0", models=("toy-a", "toy-b"), timeout_s=3.0)
            assert wait_for(lambda: router.routing.table.routes.get("toy-a") == ["ex0"], 5), \
                "the router did not install the table"
            served = router.routing.table

            ex0 = dealer(ctx, b"ex0", cfg.router.backend)
            ex0.send(b"")
            socks.append(ex0)
            arm = dealer(ctx, b"arm", cfg.router.bind)
            socks.append(arm)
            time.sleep(0.2)

            # The control plane restarts (a new process, the same address); ex0 keeps serving.
            st.restart_plane()
            # Until the router has polled the new control plane (and been sent its v0) there is nothing to check.
            assert wait_for(st.router_polled, 10), "the router never polled the new control plane"
            time.sleep(0.3)  # a few more polls, each answered with v0
            assert router.routing.table == served, "the router installed the new control plane's empty table"

            arm.send_multipart(request("r1"))
            assert ex0.poll(3000), f"not forwarded: {decode(arm.recv_multipart()) if arm.poll(100) else 'no answer'}"
            robot, *body = ex0.recv_multipart()
            assert robot == b"arm" and decode(body).id == "r1"
            assert not arm.poll(100) or not isinstance(decode(arm.recv_multipart()), ErrorReply)
        finally:
            for sock in socks:
                sock.close(linger=0)


def test_the_restarted_control_planes_first_table_is_installed_even_under_the_old_version(tmp_path):
    """The router keeps its table over the new control plane's v0, but the new one's later tables count
    again from v1: one numbered like the table the router kept (here v1, another executor now) must still
    be installed. The control plane sends a table only when the router reports another version, so the
    router routed by the old plane's table for good (and `status` said the router was up to date)."""
    with stack(tmp_path) as st:
        router = st.router
        st.register("ex0", "i0")
        assert wait_for(lambda: router.routing.table.routes.get("toy-a") == ["ex0"], 5), router.routing.table
        assert router.routing.table.version == 1

        st.restart_plane()
        # The router has polled the new control plane (and kept its table over the empty v0).
        assert wait_for(st.router_polled, 5)
        assert router.routing.table.routes.get("toy-a") == ["ex0"]
        assert st.register("ex1", "i1")["version"] == 1
        assert wait_for(lambda: router.routing.table.routes.get("toy-a") == ["ex1"], 5), router.routing.table


def test_the_restarted_control_planes_table_is_installed_when_the_router_never_saw_its_v0(tmp_path):
    """The router asks a restarted control plane for its table only once it has reconnected (its polls are
    dropped meanwhile, IMMEDIATE), while an executor's queued heartbeats reach the plane at once and make it
    register: the plane can be past v0 by the router's first poll. A table numbered like the one the router
    kept (v1 here, another executor) was then never sent, as no v0 told the router the plane had restarted:
    it routed by the old plane's table for good, and `status` said it was up to date."""
    # Holds the router's loop (no polls) while the control plane restarts and an executor registers with it.
    running = threading.Event()
    running.set()
    with stack(tmp_path, hold=running) as st:
        router = st.router
        st.register("ex0", "i0")
        assert wait_for(lambda: router.routing.table.routes.get("toy-a") == ["ex0"], 5), router.routing.table
        assert router.routing.table.version == 1

        running.clear()
        time.sleep(0.3)  # the loop is held now
        st.restart_plane()
        assert st.register("ex1", "i1")["version"] == 1
        running.set()
        assert wait_for(lambda: router.routing.table.routes.get("toy-a") == ["ex1"], 5), router.routing.table


def test_a_restarted_control_plane_holds_its_table_until_the_executors_are_back(tmp_path):
    """After a control-plane restart the executors that kept running register again one by one, each on its
    next heartbeat. The new plane published a table at the first registration, without the others: the
    router dropped them from its routes and failed the requests they were computing. Now the plane holds
    its table back until every configured executor is back (or a few heartbeat intervals have passed)."""
    with stack(tmp_path, heartbeat_s=2.0) as st:  # the plane holds its table for up to 6 s after it starts
        cfg, ctx, router = st.plane[0], st.ctx, st.router
        socks = []
        try:
            st.register("ex0", "i0", models=("toy-a",))
            st.register("ex1", "i1", models=("toy-b",))
            assert wait_for(lambda: router.routing.table.routes == {"toy-a": ["ex0"], "toy-b": ["ex1"]}, 5), \
                router.routing.table
            ex1, arm = forward_r1(ctx, cfg, b"ex1", "toy-b", socks)

            # The control plane restarts while ex1 computes r1; ex0 registers again at once, ex1 a moment later.
            st.restart_plane()
            st.register("ex0", "i0", models=("toy-a",))
            assert wait_for(st.router_polled, 5), "the router never polled the new control plane"
            time.sleep(0.5)  # a few more polls
            assert router.routing.table.routes.get("toy-b") == ["ex1"], router.routing.table
            assert not arm.poll(100), f"r1 was failed: {decode(arm.recv_multipart())}"
            status = control_status(st.address, 1, ctx)
            assert status is not None and status["settling"] is True

            st.register("ex1", "i1", models=("toy-b",))
            # Every configured executor is back: the new plane's table goes out at once, not after the hold.
            assert wait_for(lambda: router.routing.table.version == 2, 1.5), router.routing.table
            assert router.routing.table.routes == {"toy-a": ["ex0"], "toy-b": ["ex1"]}
            ex1.send_multipart([b"arm", *encode(InferReply(id="r1", model="toy-b", actions=np.zeros((2, 2), np.float32)))])
            assert arm.poll(2000), "the answer to r1 did not reach the robot"
            assert isinstance(decode(arm.recv_multipart()), InferReply)
        finally:
            for sock in socks:
                sock.close(linger=0)


def test_a_restarted_control_plane_publishes_without_an_executor_that_does_not_come_back(tmp_path):
    """The hold is bounded: an executor that does not register again within it is gone."""
    with stack(tmp_path, heartbeat_s=0.5) as st:  # a hold of 1.5 s
        router = st.router
        st.register("ex0", "i0", models=("toy-a",))
        st.register("ex1", "i1", models=("toy-b",))
        assert wait_for(lambda: router.routing.table.routes == {"toy-a": ["ex0"], "toy-b": ["ex1"]}, 5)
        st.restart_plane()
        started = time.monotonic()
        st.register("ex0", "i0", models=("toy-a",))
        assert wait_for(lambda: router.routing.table.routes.get("toy-b") == [], 5), router.routing.table
        assert time.monotonic() - started >= 1.0, "published before the hold was over"
        assert router.routing.table.routes.get("toy-a") == ["ex0"]
        status = control_status(st.address, 1, st.ctx)
        assert status is not None and status["settling"] is False


def test_a_restarted_control_plane_also_waits_for_the_replicas_the_router_routes_to(tmp_path):
    """Replicas scaled out beside the config (docker compose --scale) are known to a restarted control plane
    only from the router, which names the executors of the table it kept: the plane published as soon as the
    configured executors were back, and the router failed the replica's requests in flight."""
    with stack(tmp_path, heartbeat_s=2.0) as st:  # a hold of up to 6 s
        cfg, ctx, router = st.plane[0], st.ctx, st.router
        socks = []
        try:
            st.routed({"ex0": "toy-b", "ex1": "toy-b", "ex9": "toy-a"})  # ex9: a replica, not in the config
            _, arm = forward_r1(ctx, cfg, b"ex9", "toy-a", socks)

            st.restart_plane()
            assert wait_for(st.router_polled, 5), "the router never polled the new control plane"
            st.register("ex0", "i0", models=("toy-b",))
            st.register("ex1", "i1", models=("toy-b",))  # every configured executor is back, the replica not yet
            time.sleep(0.5)
            assert not arm.poll(100), f"r1 was failed: {decode(arm.recv_multipart())}"
            assert router.routing.table.routes.get("toy-a") == ["ex9"], router.routing.table
            st.register("ex9", "i9", models=("toy-a",))
            assert wait_for(lambda: router.routing.table.routes == {"toy-a": ["ex9"], "toy-b": ["ex0", "ex1"]}, 1.5), \
                router.routing.table
            assert not arm.poll(100), "r1 was failed"
        finally:
            for sock in socks:
                sock.close(linger=0)


def test_an_executor_that_withdraws_while_the_plane_holds_its_table_is_routed_nothing_new_at_once(tmp_path):
    """An executor that shuts down drains itself and waits a few seconds (ExecutorIO.WITHDRAW_ACK_S) for the
    router to route by a table without it. A plane holding its first table sent none, so the executor left
    while the router still routed to it. A drain (or any change) now ends the hold."""
    with stack(tmp_path, heartbeat_s=2.0) as st:  # a hold of up to 6 s, longer than the executor waits
        router = st.router
        st.register("ex0", "i0", models=("toy-a",))
        st.register("ex1", "i1", models=("toy-b",))
        assert wait_for(lambda: router.routing.table.routes.get("toy-a") == ["ex0"], 5)
        st.restart_plane()
        st.register("ex0", "i0", models=("toy-a",))  # ex1 does not come back
        assert wait_for(st.router_polled, 5)
        reply = control_request(st.address, "drain", timeout_s=2, context=st.ctx, executor="ex0")
        assert reply is not None and reply["kind"] == "ok", reply
        assert wait_for(lambda: (control_status(st.address, 1, st.ctx) or {}).get("router", {}).get("version")
                        == reply["version"], 2.0), "the router did not take the table without ex0"
        assert "ex0" not in router.routing.table.routes.get("toy-a", []), router.routing.table


def test_a_departure_during_the_hold_does_not_end_it(tmp_path):
    """Any deregister ended the hold, even one from an executor the new plane never registered (one stopped
    during its start-up deregisters too): the table went out without the executors still on their way back,
    and the router failed their requests in flight."""
    with stack(tmp_path, heartbeat_s=2.0) as st:  # a hold of up to 6 s
        cfg, ctx, router = st.plane[0], st.ctx, st.router
        socks = []
        try:
            st.routed({"ex0": "toy-a", "ex1": "toy-b", "ex9": "toy-a"})
            _, arm = forward_r1(ctx, cfg, b"ex1", "toy-b", socks)
            st.restart_plane()
            assert wait_for(st.router_polled, 5)
            st.register("ex0", "i0", models=("toy-a",))
            assert control_request(st.address, "deregister", timeout_s=0.3, context=ctx, executor="ex9") is None
            time.sleep(0.8)  # past the routers' grace: only ex1 is awaited now
            assert (control_status(st.address, 1, ctx) or {}).get("settling") is True
            assert not arm.poll(100), f"r1 was failed: {decode(arm.recv_multipart())}"
            st.register("ex1", "i1", models=("toy-b",))
            assert wait_for(lambda: router.routing.table.routes == {"toy-a": ["ex0"], "toy-b": ["ex1"]}, 1.5), \
                router.routing.table
        finally:
            for sock in socks:
                sock.close(linger=0)


def hold_state(tmp_path, heartbeat_s: float = 100.0):
    path, data = cluster_config(tmp_path)
    data["control"]["heartbeat_s"] = heartbeat_s
    path.write_text(yaml.safe_dump(data))
    return ClusterState(load_config(path))


def test_every_router_that_noticed_the_restart_names_its_executors_within_the_grace(tmp_path):
    """With two routers, the first to poll decided: a fresh one naming nobody ended the hold as soon as the
    configured executors were back, before the router that kept a table named its replica."""
    st = hold_state(tmp_path)
    info = {"toy-a": ModelInfo.from_wire(TOY_INFO)}
    t0 = st.started
    st.register("ex0", "cpu", info, now=t0)
    st.register("ex1", "cpu", info, now=t0)
    st.hear_router(-1, [], now=t0 + 0.1)  # a fresh router
    assert not st.settled(t0 + 0.2)
    st.hear_router(-1, ["ex0", "ex1", "ex9"], now=t0 + 0.3)  # the router that kept a table, a replica in it
    assert not st.settled(t0 + 0.1 + ROUTERS_GRACE_S + 0.1), "published without the replica"
    st.register("ex9", "cpu", info, now=t0 + 1.0)
    assert st.settled(t0 + 1.0)


def test_the_names_routers_add_to_the_hold_are_bounded(tmp_path):
    """Every table_get added its names for good, settled or not, up to 2**20 a message: the plane's memory."""
    st = hold_state(tmp_path)
    st.hear_router(-1, [f"ex{i}" for i in range(MAX_AWAITED + 10)] + ["x" * 300, 7, None], now=st.started)
    assert len(st.awaited) == MAX_AWAITED and all(isinstance(n, str) and len(n) <= 255 for n in st.awaited)
    st.hear_router(-1, ["more"], now=st.started)
    assert "more" not in st.awaited
    st.settle()
    before = set(st.awaited)
    st.hear_router(-1, ["late"], now=st.started)
    assert st.awaited == before
    assert st.settled()
