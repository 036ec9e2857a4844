"""A robot that comes back under the same robot_id (its process restarted, or it made a new RobotClient after
a timeout) must not reuse the request ids of the client before it.

The router tells requests apart by (socket identity, id) and hands a reconnecting identity's replies to the
new connection (ROUTER_HANDOVER), and the router's request_timeout_s (30 s) outlasts the client's timeout_s
(10 s). The SDK used to number its ids from 0 in every client ("arm-0", "arm-1", ...), so the new client's
first requests either collided with the old ones still in flight (refused BAD_REQUEST, "do not retry") or, once
the old request was answered, were paired with the old request's actions: actions computed for another
observation. Real router loop (RouterThread), real SDK; the executor is a DEALER the test drives.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import zmq

from shared.client import RequestTimeout, RobionError, RobotClient, wait_any
from shared.protocol import ErrorCode, InferReply, decode, encode
from tests.test_router_robustness import INFO, RouterThread, one_executor_table


def observation() -> tuple[dict[str, np.ndarray], np.ndarray]:
    return ({c: np.zeros(INFO.image_shape, np.uint8) for c in INFO.cameras}, np.zeros(INFO.state_dim, np.float32))


def receive(executor: zmq.Socket) -> tuple[bytes, object]:
    assert executor.poll(3000), "the request did not reach the executor"
    robot, *body = executor.recv_multipart()
    return robot, decode(body).id


def answer(executor: zmq.Socket, robot: bytes, rid, value: float) -> None:
    actions = np.full((INFO.horizon, INFO.action_dim), value, np.float32)
    executor.send_multipart([robot, *encode(InferReply(id=rid, model="toy-a", actions=actions))])


def poll_all(client: RobotClient, timeout_s: float) -> list:
    """What ``client.poll`` returns until nothing is pending or ``timeout_s`` has passed."""
    got: list = []
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and client.pending():
        got += client.poll(0.2)
    return got


def test_a_new_client_is_not_given_the_old_clients_actions(tmp_path):
    images, state = observation()
    with RouterThread(tmp_path, one_executor_table()) as rt:
        ex = rt.executor(b"ex0", rcvhwm=0)
        old = RobotClient(rt.cfg.router.bind, robot_id="arm", timeout_s=0.3, context=rt.ctx)
        old_rid = old.submit("toy-a", images, state)
        robot, rid = receive(ex)
        assert rid == old_rid
        [timed_out] = old.poll(2.0)  # the executor is slow: the old client gives up and is replaced
        assert isinstance(timed_out.error, RequestTimeout)
        old.close()

        with RobotClient(rt.cfg.router.bind, robot_id="arm", timeout_s=3.0, context=rt.ctx) as new:
            time.sleep(0.3)  # connected: the identity "arm" is now this client's (no ping: it would take an id)
            answer(ex, robot, old_rid, 1.0)  # the old request's actions, for the old observation
            time.sleep(0.3)  # forwarded by the router to the identity's connection: the new client
            new_rid = new.submit("toy-a", images, state)
            robot, rid = receive(ex)
            assert rid == new_rid
            answer(ex, robot, new_rid, 0.0)
            got = poll_all(new, 3.0)
            assert [(c.request_id, c.ok) for c in got] == [(new_rid, True)], got
            assert np.all(got[0].actions == 0.0), "the new request got the old request's actions"


def test_a_new_client_is_not_refused_for_the_old_clients_requests_in_flight(tmp_path):
    images, state = observation()
    with RouterThread(tmp_path, one_executor_table()) as rt:
        ex = rt.executor(b"ex0", rcvhwm=0)
        old = RobotClient(rt.cfg.router.bind, robot_id="arm", timeout_s=0.3, context=rt.ctx)
        old.submit("toy-a", images, state)
        receive(ex)  # held by the executor: still in flight at the router (request_timeout_s 30 s)
        old.close()  # the robot process restarts

        with RobotClient(rt.cfg.router.bind, robot_id="arm", timeout_s=3.0, context=rt.ctx) as new:
            new_rid = new.submit("toy-a", images, state)
            robot, rid = receive(ex)  # it used to be refused BAD_REQUEST "already in flight" instead
            assert rid == new_rid
            answer(ex, robot, new_rid, 0.0)
            got = poll_all(new, 3.0)
            assert [(c.request_id, c.ok) for c in got] == [(new_rid, True)], [(c.request_id, c.error) for c in got]


def test_an_id_used_again_after_its_answer_keeps_both_outcomes(tmp_path):
    """An id is unique only among requests in flight, so a robot may use it again once answered. An answer
    that a blocking call (ping, infer, metadata) read off the socket waits in the client until poll(); one for
    a later request with the same id used to overwrite it there, so poll() returned one outcome for two
    requests (and pending() went from 2 to 0)."""
    images, state = observation()
    with RouterThread(tmp_path, one_executor_table()) as rt:
        rt.answering_executor(b"ex0")
        with RobotClient(rt.cfg.router.bind, robot_id="arm", timeout_s=3.0, context=rt.ctx) as c:
            for _ in range(2):
                c.submit("toy-a", images, state, request_id="step")
                assert c.socket.poll(5000), "no reply"  # its reply is waiting on the socket ...
                c.ping()  # ... and the ping reads it while waiting for its pong
            assert c.pending() == 2
            got = c.poll(0.5)
            assert [(x.request_id, x.ok) for x in got] == [("step", True), ("step", True)]
            assert c.pending() == 0


@pytest.mark.parametrize("rid", [0, 7])
def test_an_int_id_given_by_the_caller_is_used_as_is(tmp_path, rid):
    """The protocol allows int ids, 0 included; submit used to replace a falsy one with a generated id."""
    images, state = observation()
    with RouterThread(tmp_path, one_executor_table()) as rt:
        rt.answering_executor(b"ex0")
        with RobotClient(rt.cfg.router.bind, robot_id="arm", timeout_s=3.0, context=rt.ctx) as c:
            assert c.submit("toy-a", images, state, request_id=rid) == rid
            got = poll_all(c, 3.0)
            assert [(x.request_id, x.ok) for x in got] == [(rid, True)], got


def test_an_id_given_up_on_is_refused_until_its_late_answer_has_come(tmp_path):
    """A caller's id whose request timed out in the client is still in flight at the router (request_timeout_s
    outlasts the client's timeout_s). Sent again under it, a retry was paired with the older request's late
    answer: actions computed for the older observation, handed over as the retry's. The SDK now refuses the id
    (BAD_REQUEST, as docs/protocol.md asks: give a retry a fresh id) until that late answer has arrived."""
    images, state = observation()
    with RouterThread(tmp_path, one_executor_table()) as rt:
        ex = rt.executor(b"ex0", rcvhwm=0)
        with RobotClient(rt.cfg.router.bind, robot_id="arm", timeout_s=0.3, context=rt.ctx) as c:
            c.submit("toy-a", images, state, request_id="step")
            robot, rid = receive(ex)
            [timed_out] = c.poll(2.0)
            assert isinstance(timed_out.error, RequestTimeout)
            with pytest.raises(RobionError) as refused:
                c.submit("toy-a", images, state, request_id="step")
            assert refused.value.code == ErrorCode.BAD_REQUEST and "fresh id" in refused.value.message
            # A blocking call that gives up abandons its request the same way.
            with pytest.raises(RequestTimeout):
                c.infer("toy-a", images, state, timeout_s=0.2)
            blocked_robot, blocked_rid = receive(ex)

            answer(ex, robot, "step", 1.0)  # the late answer, for the older observation: dropped
            assert c.poll(0.5) == []
            c.timeout_s = 3.0
            assert c.submit("toy-a", images, state, request_id="step") == "step"  # now the id is free again
            robot, rid = receive(ex)
            assert rid == "step"
            answer(ex, robot, "step", 0.0)
            got = poll_all(c, 3.0)
            assert [(x.request_id, x.ok) for x in got] == [("step", True)], got
            assert np.all(got[0].actions == 0.0), "the retry got the older request's actions"
            with pytest.raises(RobionError, match="fresh id"):  # the infer's answer never came
                c.submit("toy-a", images, state, request_id=blocked_rid)


def test_wait_any_waits_past_a_late_answer_it_drops(tmp_path):
    """A late answer to a request already timed out makes the socket readable but completes nothing:
    wait_any returned [] at once, long before its timeout and before any completion."""
    images, state = observation()
    with RouterThread(tmp_path, one_executor_table()) as rt:
        ex = rt.executor(b"ex0", rcvhwm=0)
        with RobotClient(rt.cfg.router.bind, robot_id="arm", timeout_s=0.5, context=rt.ctx) as c:
            old = c.submit("toy-a", images, state)
            robot, _ = receive(ex)
            [timed_out] = c.poll(2.0)
            assert timed_out.request_id == old and isinstance(timed_out.error, RequestTimeout)
            new = c.submit("toy-a", images, state)
            receive(ex)  # held: never answered
            answer(ex, robot, old, 1.0)  # the late answer, dropped by the client
            assert c.socket.poll(2000), "the late answer did not arrive"
            t0 = time.monotonic()
            got = wait_any([c], 5.0)
            waited = time.monotonic() - t0
            assert [(x.request_id, type(x.error)) for _, x in got] == [(new, RequestTimeout)], got
            assert waited > 0.2, f"returned after {waited:.3f} s"


def test_camera_names_the_router_cannot_read_fail_at_once(tmp_path):
    """Camera names that are not strings make the router's header decoder fail before it reads the id: its
    answer carried id "" and the request waited out its whole timeout. The SDK refuses them before sending."""
    images, state = observation()
    with RouterThread(tmp_path, one_executor_table()) as rt:
        rt.answering_executor(b"ex0")
        with RobotClient(rt.cfg.router.bind, robot_id="arm", timeout_s=3.0, context=rt.ctx) as c:
            t0 = time.monotonic()
            with pytest.raises(RobionError) as e:
                c.infer("toy-a", dict(enumerate(images.values())), state)
            assert e.value.code == ErrorCode.BAD_REQUEST and time.monotonic() - t0 < 1.0
            assert c.pending() == 0
            assert c.infer("toy-a", images, state).ok
