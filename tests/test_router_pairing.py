"""A reply is the answer to the request the router forwarded to that executor, and to no other.

An id is unique only among a robot's requests in flight (docs/protocol.md): once a request is answered, even
UNAVAILABLE by the router itself (its executor did not answer within request_timeout_s, or left the routing
table), the robot may send a new request under the same id, and retrying is what UNAVAILABLE asks for. The
retry may go to another executor. The first executor may still be alive and answer the old request late;
the router used to take that answer for the retry's, so the robot got actions computed for an older
observation, and the retry's own answer was then dropped. Real router loop (RouterThread); the executors
are DEALERs the test drives.
"""

from __future__ import annotations

import numpy as np

from shared.control import RoutingTable
from shared.protocol import ErrorCode, ErrorReply, InferReply, decode
from tests.test_client_ids import answer, receive
from tests.test_router_robustness import INFO, RouterThread, infer_frames

TWO = RoutingTable(version=1, models={"toy-a": INFO}, routes={"toy-a": ["ex0", "ex1"]}, executors=["ex0", "ex1"])


def test_a_late_answer_from_another_executor_does_not_answer_the_retry(tmp_path):
    with RouterThread(tmp_path, TWO, request_timeout_s=0.3) as rt:
        ex0, ex1 = rt.executor(b"ex0", rcvhwm=0), rt.executor(b"ex1", rcvhwm=0)
        arm = rt.robot(b"arm")
        arm.send_multipart(infer_frames("r1"))  # round-robin: to ex0, which is slow
        robot, rid = receive(ex0)
        assert arm.poll(3000), "no answer after request_timeout_s"
        timed_out = decode(arm.recv_multipart())
        assert isinstance(timed_out, ErrorReply) and timed_out.code == ErrorCode.UNAVAILABLE

        arm.send_multipart(infer_frames("r1"))  # the retry, same id: to ex1
        robot1, rid1 = receive(ex1)
        assert rid1 == "r1"
        answer(ex0, robot, rid, 1.0)  # ex0 finally answers the first request
        answer(ex1, robot1, rid1, 0.0)
        assert arm.poll(3000), "no answer to the retry"
        got = decode(arm.recv_multipart())
        assert isinstance(got, InferReply) and got.id == "r1"
        assert np.all(got.actions == 0.0), "the retry was answered with the first request's actions (from ex0)"
        assert not arm.poll(300), "a second answer to one request"
        assert rt.router.in_flight == {}
