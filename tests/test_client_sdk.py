"""The robot SDK where integrators trip: two clients of one robot, buffers reused after submit, timeouts
(short, infinite, interrupted), a large metadata answer, and inputs that cannot travel.

Real Router loop (RouterThread) or a bare ROUTER socket on loopback TCP, real SDK.
"""

from __future__ import annotations

import contextlib
import math
import time

import numpy as np
import pytest
import zmq

from shared.client import RobionError, RobotClient, wait_any
from shared.control import RoutingTable
from shared.protocol import ErrorCode, ModelInfo, decode
from tests.helpers import free_ports
from tests.test_router_large_table import INFO as VARIANT_INFO
from tests.test_router_large_table import big_table
from tests.test_router_robustness import INFO, RouterThread, one_executor_table


def observation() -> tuple[dict[str, np.ndarray], np.ndarray]:
    return ({c: np.zeros(INFO.image_shape, np.uint8) for c in INFO.cameras}, np.zeros(INFO.state_dim, np.float32))


@contextlib.contextmanager
def inproc_router(name: str):
    """A bare ROUTER socket on inproc://NAME and the context a client must share to reach it. Over inproc a
    message is handed to the peer as it is, with no I/O thread in between."""
    ctx = zmq.Context()
    router = ctx.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    router.bind(f"inproc://{name}")
    try:
        yield ctx, router
    finally:
        ctx.destroy(linger=0)  # closes a client a failed assertion left open too, which term() would wait on


def test_two_clients_of_one_robot_each_get_their_own_answers(tmp_path):
    # A robot with a thread per arm makes a client per thread under its one robot_id. Sharing one socket
    # identity, the router handed every answer to the newer connection and the older timed out on all of its.
    images, state = observation()
    with RouterThread(tmp_path, one_executor_table()) as rt:
        rt.answering_executor(b"ex0")
        with RobotClient(rt.cfg.router.bind, robot_id="arm", timeout_s=3.0, context=rt.ctx) as first, \
                RobotClient(rt.cfg.router.bind, robot_id="arm", timeout_s=3.0, context=rt.ctx) as second:
            assert first.infer("toy-a", images, state).ok
            assert second.infer("toy-a", images, state).ok
            for _ in range(3):
                assert first.infer("toy-a", images, state).ok and second.infer("toy-a", images, state).ok


def test_a_robot_is_pinned_by_its_name_not_its_connection(tmp_path):
    # Two executors with room for one robot each: both clients of "arm" go where "arm" is pinned (it counts
    # once against the quota), and another robot takes the other executor.
    table = RoutingTable(version=1, models={"toy-a": INFO}, routes={"toy-a": ["ex0", "ex1"]},
                         quotas={"toy-a": {"ex0": 1, "ex1": 1}}, executors=["ex0", "ex1"])
    images, state = observation()
    with RouterThread(tmp_path, table) as rt:
        executors = {name: rt.executor(name.encode(), rcvhwm=0) for name in ("ex0", "ex1")}
        clients = [RobotClient(rt.cfg.router.bind, robot_id=r, timeout_s=3.0, context=rt.ctx)
                   for r in ("arm", "arm", "other")]
        try:
            went = []
            for c in clients:
                rid = c.submit("toy-a", images, state)
                deadline = time.monotonic() + 3
                while not any(s.poll(0) for s in executors.values()) and time.monotonic() < deadline:
                    time.sleep(0.01)
                [name] = [n for n, s in executors.items() if s.poll(0)]
                _, *body = executors[name].recv_multipart()
                assert decode(body).id == rid
                went.append(name)
            assert went[0] == went[1] != went[2]
        finally:
            for c in clients:
                c.close()


def test_submit_copies_the_arrays_it_is_given():
    # Images above pyzmq's zero-copy threshold (64 KiB) were sent from the caller's buffer when the message
    # left, maybe after a camera loop had written its next frame into it. Over inproc a message is handed to
    # the peer as it is, so a zero-copy send would show the new frame here.
    info = ModelInfo(cameras=["cam0"], image_shape=[224, 224, 3], state_dim=8, horizon=10, action_dim=7,
                     deadline_ms=500.0, arch="toy")
    with inproc_router("copies") as (ctx, router):
        with RobotClient("inproc://copies", robot_id="cam", timeout_s=5.0, context=ctx) as client:
            frame = np.full(info.image_shape, 7, np.uint8)
            rid = client.submit("toy-a", {"cam0": frame}, np.zeros(info.state_dim, np.float32))
            frame[:] = 255  # the next camera frame, into the same buffer
            assert router.poll(5000), "the request never arrived"
            _, *body = router.recv_multipart()
            req = decode(body)
            assert req.id == rid and int(req.images["cam0"].min()) == int(req.images["cam0"].max()) == 7


def test_infer_keeps_its_own_timeout_while_it_fetches_camera_names():
    # Images as a list need the model's camera names, from metadata(): that round trip waited the client's
    # timeout (5 s here), not the 0.3 s infer was given. Nothing listens at this address.
    [port] = free_ports(1)
    images, state = observation()
    with RobotClient(f"tcp://127.0.0.1:{port}", robot_id="slow", timeout_s=5.0) as c:
        t0 = time.monotonic()
        with pytest.raises(RobionError) as err:
            c.infer("toy-a", list(images.values()), state, timeout_s=0.3)
        assert err.value.code == ErrorCode.UNAVAILABLE and "not reachable" in err.value.message
        assert 0.25 < time.monotonic() - t0 < 1.0 and c.pending() == 0


def test_an_infinite_timeout_waits_without_failing(tmp_path):
    images, state = observation()
    with RouterThread(tmp_path, one_executor_table()) as rt:
        rt.answering_executor(b"ex0")
        with RobotClient(rt.cfg.router.bind, robot_id="patient", timeout_s=math.inf, context=rt.ctx) as c:
            assert set(c.metadata()) == {"toy-a"}
            assert c.ping(timeout_s=math.inf) >= 0
            assert c.infer("toy-a", list(images.values()), state).ok
            c.submit("toy-a", images, state)
            got = []
            while not got:
                got = wait_any([c], math.inf)
            assert [done.ok for _, done in got] == [True] and c.pending() == 0


def test_an_interrupted_wait_leaves_no_request_behind(tmp_path, monkeypatch):
    with RouterThread(tmp_path, one_executor_table()) as rt:
        with RobotClient(rt.cfg.router.bind, robot_id="ctrl-c", timeout_s=3.0, context=rt.ctx) as c:
            def interrupted() -> None:
                raise KeyboardInterrupt

            monkeypatch.setattr(c, "_receive_one", interrupted)
            with pytest.raises(KeyboardInterrupt):
                c.metadata()
            monkeypatch.undo()
            assert c.pending() == 0 and c.poll(0.5) == []  # the late metadata answer is no completion


def test_metadata_of_hundreds_of_models_reaches_the_robot(tmp_path):
    # 500 models make a metadata answer of about 70 KB, over a request header's 64 KiB: the SDK dropped it as
    # undecodable, and metadata() timed out with no word of why.
    with RouterThread(tmp_path, big_table(500, 64, 2)) as rt:
        with RobotClient(rt.cfg.router.bind, robot_id="big", timeout_s=3.0, context=rt.ctx) as c:
            models = c.metadata()
            assert len(models) == 500 and models["pi0-factory-variant-0499"] == VARIANT_INFO


@pytest.mark.parametrize("images,instruction,message", [
    ({"cam0": np.zeros((64, 64, 3), np.uint16), "cam1": np.zeros((64, 64, 3), np.uint8)}, "go", "dtype uint16"),
    ({"cam0": np.zeros((64, 64, 3), np.uint8), "cam1": np.zeros((64, 64, 3), np.uint8)}, "go \udc80", "utf-8"),
])
def test_inputs_that_cannot_travel_are_robion_errors(images, instruction, message):
    [port] = free_ports(1)
    with RobotClient(f"tcp://127.0.0.1:{port}", robot_id="odd", timeout_s=1.0) as c:
        with pytest.raises(RobionError, match=message) as exc:
            c.submit("toy-a", images, np.zeros(8, np.float32), instruction)
        assert exc.value.code == ErrorCode.BAD_REQUEST and c.pending() == 0


@pytest.mark.parametrize("state,message", [
    (np.full(8, 1 + 2j), "real numbers"),  # the cast to float32 dropped the imaginary part, silently
    (np.full(8, 1e39), "beyond float32's range"),  # the server refused it as "NaN or infinity"
    ([10**39] * 8, "beyond float32's range"),  # ints past int64: an object array
])
def test_a_state_the_wire_cannot_carry_faithfully_is_refused_saying_why(state, message):
    images = {"cam0": np.zeros((8, 8, 3), np.uint8)}
    with inproc_router("odd-state") as (ctx, router):
        with RobotClient("inproc://odd-state", robot_id="odd", timeout_s=1.0, context=ctx) as c:
            with pytest.raises(RobionError, match=message) as exc:
                c.submit("toy-a", images, state, "go")
            assert exc.value.code == ErrorCode.BAD_REQUEST and c.pending() == 0
            # float64 within range, ints and lists still travel, as float32 (NaN is the server's to refuse)
            for i, fine in enumerate((np.full(8, 1e38), np.arange(8), [0.5] * 8, np.full(8, np.nan))):
                c.submit("toy-a", images, fine, request_id=i)
                assert router.poll(5000)
                sent = decode(router.recv_multipart()[1:]).state
                assert sent.dtype == np.float32 and np.array_equal(sent, np.asarray(fine, np.float32), equal_nan=True)


def test_an_empty_id_is_refused_before_sending():
    """"" is the id of the router's answers to requests it could not read: a request sent under it could be
    handed another request's error."""
    with inproc_router("empty-id") as (ctx, router):
        with RobotClient("inproc://empty-id", robot_id="odd", timeout_s=1.0, context=ctx) as c:
            images = {"cam0": np.zeros((8, 8, 3), np.uint8)}
            with pytest.raises(RobionError, match="non-empty") as exc:
                c.submit("toy-a", images, np.zeros(4, np.float32), request_id="")
            assert exc.value.code == ErrorCode.BAD_REQUEST and c.pending() == 0
            assert c.submit("toy-a", images, np.zeros(4, np.float32), request_id=0) == 0  # 0 is an id
            assert router.poll(5000) and decode(router.recv_multipart()[1:]).id == 0


def test_a_request_is_never_queued_for_a_router_that_is_away():
    """Requests sent while no router was connected waited in the socket: poll() reported them timed out, and they
    reached the router when it came back, to run on old observations (holding their images meanwhile)."""
    [port] = free_ports(1)
    address = f"tcp://127.0.0.1:{port}"
    images, state = {"cam0": np.zeros((224, 224, 3), np.uint8)}, np.zeros(8, np.float32)
    ctx = zmq.Context()
    try:
        with RobotClient(address, robot_id="away", timeout_s=0.3, context=ctx, connect_timeout_s=0.2) as c:
            t0 = time.monotonic()
            with pytest.raises(RobionError) as err:  # a new client waits for its first connection, then fails
                c.submit("toy-a", images, state)
            assert err.value.code == ErrorCode.UNAVAILABLE and 0.15 < time.monotonic() - t0 < 1.0
            t0 = time.monotonic()
            with pytest.raises(RobionError):  # and from then on fails at once
                c.submit("toy-a", images, state)
            assert time.monotonic() - t0 < 0.1 and c.pending() == 0
            t0 = time.monotonic()
            with pytest.raises(RobionError) as err:  # a blocking call waits for a connection within its timeout
                c.ping(timeout_s=0.3)
            assert err.value.code == ErrorCode.UNAVAILABLE and 0.25 < time.monotonic() - t0 < 1.0
            router = ctx.socket(zmq.ROUTER)
            router.setsockopt(zmq.LINGER, 0)
            router.bind(address)
            try:
                deadline = time.monotonic() + 5.0
                while True:  # the client reconnects on its own (every 100 ms)
                    try:
                        rid = c.submit("toy-a", images, state)
                        break
                    except RobionError:
                        assert time.monotonic() < deadline, "the client never reconnected"
                        time.sleep(0.05)
                assert router.poll(2000) and decode(router.recv_multipart()[1:]).id == rid
                assert not router.poll(300), "a request the client had failed reached the router"
            finally:
                router.close()
    finally:
        ctx.term()


def test_close_ends_the_requests_in_flight():
    """close() left its requests counted in pending() for good, and poll() then raised a raw ZMQError."""
    with inproc_router("close") as (ctx, router):
        c = RobotClient("inproc://close", robot_id="closing", timeout_s=5.0, context=ctx)
        images, state = {"cam0": np.zeros((8, 8, 3), np.uint8)}, np.zeros(4, np.float32)
        rids = [c.submit("toy-a", images, state) for _ in range(2)]
        c.close()
        assert c.pending() == 2  # their outcomes, until poll returns them
        done = c.poll(1.0)
        assert [d.request_id for d in done] == rids and c.pending() == 0
        assert all(d.error.code == ErrorCode.UNAVAILABLE and "closed" in d.error.message for d in done)
        assert c.poll(0.1) == [] and wait_any([c], 0.1) == []
        with pytest.raises(RobionError) as err:
            c.submit("toy-a", images, state)
        assert err.value.code == ErrorCode.BAD_REQUEST and "closed" in err.value.message


def test_an_old_model_list_does_not_fail_images_given_as_a_list(tmp_path):
    """Images as a list are matched to camera names from the cached model list. Read before the router had its
    routing table, that list was empty, and every such call failed UNKNOWN_MODEL ("never retry") for good."""
    images, state = observation()
    with RouterThread(tmp_path) as rt:  # no routing table yet: the control plane is still starting
        rt.answering_executor(b"ex0")
        with RobotClient(rt.cfg.router.bind, robot_id="early", timeout_s=2.0, context=rt.ctx) as c:
            with pytest.raises(RobionError) as err:
                c.infer("toy-a", list(images.values()), state)
            assert err.value.code == ErrorCode.UNAVAILABLE, err.value
            rt.router.routing.update(one_executor_table())
            assert c.infer("toy-a", list(images.values()), state).ok
            with pytest.raises(RobionError) as err:
                c.infer("no-such-model", list(images.values()), state)
            assert err.value.code == ErrorCode.UNKNOWN_MODEL


def test_ids_past_64_bits_and_nan_timeouts_are_robion_errors():
    [port] = free_ports(1)
    images, state = {"cam0": np.zeros((8, 8, 3), np.uint8)}, np.zeros(4, np.float32)
    with pytest.raises(ValueError, match="timeout_s"):
        RobotClient(f"tcp://127.0.0.1:{port}", timeout_s=math.nan)
    with RobotClient(f"tcp://127.0.0.1:{port}", robot_id="odd", timeout_s=1.0) as c:
        for call in (lambda: c.submit("toy-a", images, state, request_id=2**64),
                     lambda: c.infer("toy-a", images, state, timeout_s=math.nan),
                     lambda: c.metadata(timeout_s=-1.0),
                     lambda: c.poll(math.nan),
                     lambda: wait_any([c], math.nan)):
            with pytest.raises(RobionError) as err:
                call()
            assert err.value.code == ErrorCode.BAD_REQUEST
        assert c.pending() == 0
