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

import numpy as np
import zmq

from services.router.frontend import Router
from shared import control
from shared.cluster import control_request, control_status
from shared.config import dial_address
from shared.protocol import ErrorReply, InferRequest, decode, encode
from tests.helpers import TOY_INFO, cluster_config, start_control_plane, wait_for


def request(rid: str) -> list:
    images = {c: np.zeros(TOY_INFO["image_shape"], np.uint8) for c in TOY_INFO["cameras"]}
    return encode(InferRequest(id=rid, robot="arm", model="toy-a", images=images,
                               state=np.zeros(TOY_INFO["state_dim"], np.float32)))


def test_a_restarted_control_planes_empty_table_is_not_installed(tmp_path):
    path, data = cluster_config(tmp_path)
    cfg, cp_stop, cp_thread = start_control_plane(path, data)
    ctx = zmq.Context()
    router = Router(cfg, ctx)
    stop = threading.Event()
    thread = threading.Thread(target=router.run, args=(stop,), daemon=True)
    thread.start()
    socks = []
    try:
        reg = ctx.socket(zmq.DEALER)
        reg.setsockopt(zmq.LINGER, 0)
        reg.connect(dial_address(cfg.control.bind, cfg.control.connect))
        socks.append(reg)
        reg.send(control.pack("register", executor="ex0", device="cpu", instance="i0",
                              models={"toy-a": TOY_INFO, "toy-b": TOY_INFO}))
        assert reg.poll(3000) and control.unpack(reg.recv())["kind"] == "registered"
        end = time.monotonic() + 5
        while router.routing.table.routes.get("toy-a") != ["ex0"]:
            assert time.monotonic() < end, "the router did not install the table"
            time.sleep(0.05)
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
        cp_stop.set()
        cp_thread.join(5)
        cfg2, cp_stop, cp_thread = start_control_plane(path, data)
        # Until the router has polled the new control plane (and been sent its v0) there is nothing to check.
        address = dial_address(cfg2.control.bind, cfg2.control.connect)
        assert wait_for(lambda: ((control_status(address, 1, ctx) or {}).get("router") or {}).get("last_seen_s")
                        is not None, 10), "the router never polled the new control plane"
        time.sleep(0.3)  # a few more polls, each answered with v0
        assert router.routing.table == served, "the router installed the new control plane's empty table"

        arm.send_multipart(request("r1"))
        assert ex0.poll(3000), f"not forwarded: {decode(arm.recv_multipart()) if arm.poll(100) else 'no answer'}"
        robot, *body = ex0.recv_multipart()
        assert robot == b"arm" and decode(body).id == "r1"
        assert not arm.poll(100) or not isinstance(decode(arm.recv_multipart()), ErrorReply)
    finally:
        stop.set()
        thread.join(5)
        for s in socks:
            s.close(linger=0)
        cp_stop.set()
        cp_thread.join(5)
        ctx.term()


def test_the_restarted_control_planes_first_table_is_installed_even_under_the_old_version(tmp_path):
    """The router keeps its table over the new control plane's v0, but the new one's later tables count
    again from v1: one numbered like the table the router kept (here v1, another executor now) must still
    be installed. The control plane sends a table only when the router reports another version, so the
    router routed by the old plane's table for good (and `status` said the router was up to date)."""
    path, data = cluster_config(tmp_path)
    cfg, cp_stop, cp_thread = start_control_plane(path, data)
    address = dial_address(cfg.control.bind, cfg.control.connect)
    ctx = zmq.Context()
    router = Router(cfg, ctx)
    stop = threading.Event()
    thread = threading.Thread(target=router.run, args=(stop,), daemon=True)
    thread.start()
    try:
        reply = control_request(address, "register", timeout_s=5, context=ctx, executor="ex0", device="cpu",
                                instance="i0", models={"toy-a": TOY_INFO})
        assert reply is not None and reply["kind"] == "registered", reply
        assert wait_for(lambda: router.routing.table.routes.get("toy-a") == ["ex0"], 5), router.routing.table
        assert router.routing.table.version == 1

        cp_stop.set()
        cp_thread.join(5)
        cfg, cp_stop, cp_thread = start_control_plane(path, data)
        # The router has polled the new control plane (and kept its table over the empty v0).
        assert wait_for(lambda: ((control_status(address, 1, ctx) or {}).get("router") or {}).get("last_seen_s")
                        is not None, 5)
        assert router.routing.table.routes.get("toy-a") == ["ex0"]
        reply = control_request(address, "register", timeout_s=5, context=ctx, executor="ex1", device="cpu",
                                instance="i1", models={"toy-a": TOY_INFO})
        assert reply is not None and reply["kind"] == "registered" and reply["version"] == 1, reply
        assert wait_for(lambda: router.routing.table.routes.get("toy-a") == ["ex1"], 5), router.routing.table
    finally:
        stop.set()
        thread.join(5)
        cp_stop.set()
        cp_thread.join(5)
        ctx.term()


def test_the_restarted_control_planes_table_is_installed_when_the_router_never_saw_its_v0(tmp_path):
    """The router asks a restarted control plane for its table only once it has reconnected (its polls are
    dropped meanwhile, IMMEDIATE), while an executor's queued heartbeats reach the plane at once and make it
    register: the plane can be past v0 by the router's first poll. A table numbered like the one the router
    kept (v1 here, another executor) was then never sent, as no v0 told the router the plane had restarted:
    it routed by the old plane's table for good, and `status` said it was up to date."""
    path, data = cluster_config(tmp_path)
    cfg, cp_stop, cp_thread = start_control_plane(path, data)
    address = dial_address(cfg.control.bind, cfg.control.connect)
    ctx = zmq.Context()
    router = Router(cfg, ctx)
    # Holds the router's loop (no polls) while the control plane restarts and an executor registers with it.
    running = threading.Event()
    running.set()
    expire = router._expire

    def held_expire(now: float) -> None:
        running.wait(10)
        expire(now)

    router._expire = held_expire
    stop = threading.Event()
    thread = threading.Thread(target=router.run, args=(stop,), daemon=True)
    thread.start()
    try:
        reply = control_request(address, "register", timeout_s=5, context=ctx, executor="ex0", device="cpu",
                                instance="i0", models={"toy-a": TOY_INFO})
        assert reply is not None and reply["kind"] == "registered", reply
        assert wait_for(lambda: router.routing.table.routes.get("toy-a") == ["ex0"], 5), router.routing.table
        assert router.routing.table.version == 1

        running.clear()
        time.sleep(0.3)  # the loop is held now
        cp_stop.set()
        cp_thread.join(5)
        cfg, cp_stop, cp_thread = start_control_plane(path, data)
        reply = control_request(address, "register", timeout_s=5, context=ctx, executor="ex1", device="cpu",
                                instance="i1", models={"toy-a": TOY_INFO})
        assert reply is not None and reply["kind"] == "registered" and reply["version"] == 1, reply
        running.set()
        assert wait_for(lambda: router.routing.table.routes.get("toy-a") == ["ex1"], 5), router.routing.table
    finally:
        running.set()
        stop.set()
        thread.join(5)
        cp_stop.set()
        cp_thread.join(5)
        ctx.term()
