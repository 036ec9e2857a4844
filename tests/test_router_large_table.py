"""A large factory's routing table reaches the router, and the robots' header limits stay as they are.

The routing table grows with the cluster: every model's description, its routes and the traffic
controller's quota per (model, executor). A factory of 64 GPUs serving 300 fine-tuned variants, each on two
GPUs, publishes a table of about 75 KB, beyond the 64 KiB (and 1024-entry) limits a robot's request header
is held to. Control messages used to be unpacked with those robot limits, so the router refused every such
table ("kept routing table vN") and kept routing by a stale one forever, `robion up` never became ready and
`robion ctl status` failed. Here the real control plane builds and serves the table, and the real router
installs it and routes by it.
"""

from __future__ import annotations

import threading
import time

import msgpack
import numpy as np
import pytest
import zmq

from services.router.frontend import Router
from shared import control
from shared.cluster import control_status
from shared.config import dial_address
from shared.control import RoutingTable
from shared.protocol import (MAX_HEADER_BYTES, MAX_MAP_LEN, ErrorCode, InferRequest, Metadata, ModelInfo,
                             ProtocolError, decode, encode, unpack_header)
from tests.helpers import cluster_config, start_control_plane

GPUS = 64
VARIANTS = 300
INFO = ModelInfo(cameras=["base", "wrist_left", "wrist_right"], image_shape=[8, 8, 3], state_dim=4, horizon=2,
                 action_dim=2, deadline_ms=500.0, arch="toy")


def variant(i: int) -> str:
    return f"pi0-factory-variant-{i:04d}"


def factory_config(tmp_path):
    """64 CPU executors, 300 variants each on two of them; populations, so the controller publishes quotas."""
    models = [{"name": variant(i), "arch": "toy", "size": "tiny", "seed": i, "slo_ms": 500, "robots": 2, "hz": 2,
               "limit": 60} for i in range(VARIANTS)]
    executors = [{"name": f"gpu{j}", "device": "cpu", "models": [], "metrics_port": 0} for j in range(GPUS)]
    for i in range(VARIANTS):
        for j in (i % GPUS, (i + 1) % GPUS):
            executors[j]["models"].append(variant(i))
    return cluster_config(tmp_path, models=models, executors=executors)


def wait_for(cond, timeout_s: float, what: str) -> None:
    end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.05)


def test_a_large_factory_table_is_installed_by_the_router(tmp_path):
    path, data = factory_config(tmp_path)
    data["control"]["strategy"] = "eps"  # quotas in the table, without the integer program's solve time
    cfg, cp_stop, cp_thread = start_control_plane(path, data)
    ctx = zmq.Context()
    socks: list[zmq.Socket] = []

    def sock(kind: int, identity: bytes | None = None) -> zmq.Socket:
        s = ctx.socket(kind)
        s.setsockopt(zmq.LINGER, 0)
        if identity is not None:
            s.setsockopt(zmq.IDENTITY, identity)
        socks.append(s)
        return s

    router = Router(cfg, ctx)
    stop = threading.Event()
    thread = threading.Thread(target=router.run, args=(stop,), daemon=True)
    try:
        # Every executor registers its models, as a real one does on start-up.
        ex = sock(zmq.DEALER)
        ex.connect(dial_address(cfg.control.bind, cfg.control.connect))
        for e in cfg.executors:
            ex.send(control.pack("register", executor=e.name, device="cpu", instance=f"{e.name}-1",
                                 models={m: INFO.to_wire() for m in e.models}))
            assert ex.poll(5000), f"{e.name}: no answer to register"
            assert control.unpack(ex.recv())["kind"] == "registered"
        thread.start()

        def installed() -> bool:
            t = router.routing.table
            return len(t.models) == VARIANTS and all(len(t.routes.get(variant(i), [])) == 2 for i in range(VARIANTS))
        wait_for(installed, 10, "the router to install the factory's routing table")
        # `robion up` waits for this: every executor registered and the router on the current table (the
        # router reports its version with its next poll). `status` carries the table too.
        address = dial_address(cfg.control.bind, cfg.control.connect)
        wait_for(lambda: (control_status(address, timeout_s=5.0) or {}).get("ready"), 10, "the cluster to be ready")
        status = control_status(address, timeout_s=5.0)
        table = RoutingTable.from_wire(status["table"])
        assert router.routing.table == table and status["router"]["version"] == table.version
        # The table is beyond a robot header's limit: what this test is about.
        assert table.quotas, "the traffic controller published no quotas"
        assert len(control.pack("table", table=table.to_wire())) > MAX_HEADER_BYTES

        # ... and routes by it: a request for a variant reaches one of the two executors hosting it.
        model = variant(7)
        hosts = table.routes[model]
        backends = {}
        for name in hosts:
            b = sock(zmq.DEALER, name.encode())
            b.connect(cfg.router.backend)
            b.send(b"")  # makes the identity routable at the router
            backends[name] = b
        time.sleep(0.2)
        robot = sock(zmq.DEALER, b"arm-1")
        robot.connect(cfg.router.bind)
        images = {c: np.zeros(INFO.image_shape, np.uint8) for c in INFO.cameras}
        robot.send_multipart(encode(InferRequest(id="r1", robot="arm-1", model=model, images=images,
                                                 state=np.zeros(INFO.state_dim, np.float32))))
        poller = zmq.Poller()
        for b in backends.values():
            poller.register(b, zmq.POLLIN)
        arrived = dict(poller.poll(5000))
        assert arrived, f"the request for {model} reached neither of its executors {hosts}"
        (b,) = arrived
        frames = b.recv_multipart()
        assert frames[0] == b"arm-1" and msgpack.unpackb(frames[1])["id"] == "r1"
    finally:
        stop.set()
        if thread.is_alive():
            thread.join(5)
        else:
            router.close()
        for s in socks:
            s.close(linger=0)
        cp_stop.set()
        cp_thread.join(5)
        ctx.term()


def big_table(models: int, executors: int, hosts: int) -> RoutingTable:
    execs = [f"gpu{j}" for j in range(executors)]
    names = [variant(i) for i in range(models)]
    routes = {m: [execs[(i + h) % executors] for h in range(hosts)] for i, m in enumerate(names)}
    return RoutingTable(version=5, models={m: INFO for m in names}, routes=routes,
                        quotas={m: {e: 3 for e in r} for m, r in routes.items()}, limits={m: 60 for m in names},
                        executors=execs)


@pytest.mark.parametrize("models,executors,hosts", [
    (300, 64, 2),  # over 64 KiB
    (64, 64, 64),  # every model on every GPU: quotas of 64 x 64 entries
    (MAX_MAP_LEN + 100, 64, 1),  # more models than a robot header's map may hold
])
def test_control_messages_carry_tables_beyond_the_robot_header_limits(models, executors, hosts):
    table = big_table(models, executors, hosts)
    frame = control.pack("table", table=table.to_wire())
    with pytest.raises(ProtocolError):
        unpack_header(frame)  # a robot's header limits: this table does not fit them
    assert RoutingTable.from_wire(control.unpack(frame)["table"]) == table


def test_control_messages_still_have_a_limit():
    frame = control.pack("apply", config="x" * (control.MAX_CONTROL_BYTES + 1))
    with pytest.raises(ProtocolError) as e:
        control.unpack(frame)
    assert e.value.code is ErrorCode.TOO_LARGE


def test_robot_headers_keep_their_limits():
    """Only the services' own messages got larger limits; what a robot sends is held to 64 KiB and 1024 entries."""
    with pytest.raises(ProtocolError) as e:
        unpack_header(msgpack.packb({"kind": "infer", "id": "x", "pad": "x" * MAX_HEADER_BYTES}))
    assert e.value.code is ErrorCode.TOO_LARGE
    with pytest.raises(ProtocolError) as e:
        unpack_header(msgpack.packb({"kind": "infer", "id": "x", "obs": {str(i): 0 for i in range(MAX_MAP_LEN + 1)}}))
    assert e.value.code is ErrorCode.BAD_REQUEST
    # The metadata reply itself is a robot-facing header, and 300 variants fit in it.
    meta = encode(Metadata(id="h", models=big_table(VARIANTS, GPUS, 2).models))
    assert isinstance(decode(meta), Metadata)
