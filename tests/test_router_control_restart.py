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
import zmq

from services.router.frontend import Router
from shared.cluster import control_request, control_status
from shared.config import dial_address
from shared.protocol import ErrorReply, InferRequest, decode, encode
from tests.helpers import TOY_INFO, cluster_config, start_control_plane, wait_for


def request(rid: str) -> list:
    images = {c: np.zeros(TOY_INFO["image_shape"], np.uint8) for c in TOY_INFO["cameras"]}
    return encode(InferRequest(id=rid, robot="arm", model="toy-a", images=images,
                               state=np.zeros(TOY_INFO["state_dim"], np.float32)))


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

    def router_polled(self) -> bool:
        """The control plane has heard a table poll from the router."""
        status = control_status(self.address, 1, self.ctx) or {}
        return (status.get("router") or {}).get("last_seen_s") is not None


@contextmanager
def stack(tmp_path, hold: threading.Event | None = None) -> Iterator[Stack]:
    """``hold``, when given, holds the router's loop whenever it is cleared (no table polls meanwhile)."""
    path, data = cluster_config(tmp_path)
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

            ex0 = ctx.socket(zmq.DEALER)
            ex0.setsockopt(zmq.IDENTITY, b"ex0")
            ex0.setsockopt(zmq.LINGER, 0)
            ex0.connect(cfg.router.backend)
            ex0.send(b"")
            socks.append(ex0)
            arm = ctx.socket(zmq.DEALER)
            arm.setsockopt(zmq.IDENTITY, b"arm")
            arm.setsockopt(zmq.LINGER, 0)
            arm.connect(cfg.router.bind)
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
