"""The robot SDK facing replies it cannot use: an answer that arrived broken fails its request at once.

A bare ZeroMQ ROUTER socket in a thread plays the router, so each reply can be crafted byte by byte.
A reply whose header decodes and names a request in flight, but which is otherwise malformed (or is
not an answer to that request), completes the request with INTERNAL well before its timeout. A reply
with an undecodable header, or an id this client has no request for, has nothing to fail: it is
dropped, and the client goes on working.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Any, Callable

import msgpack
import numpy as np
import pytest
import zmq

from shared.client import MalformedReply, RequestTimeout, RobionError, RobotClient
from shared.protocol import (ErrorCode, ErrorReply, InferReply, Metadata, ModelInfo, Pong, Timings, decode, encode,
                             pack_header)
from tests.helpers import changed

TIMEOUT_S = 10.0  # the SDK's default: every "at once" below is well under it
PROMPT_S = 1.0
IMAGES = {"cam0": np.zeros((8, 8, 3), np.uint8)}
STATE = np.zeros(4, np.float32)
ACTIONS = np.arange(6, dtype=np.float32).reshape(2, 3)
BIG_ACTIONS = np.arange(512, dtype=np.float32).reshape(16, 32)  # 2 KiB: travels in a frame of its own

Frames = list[bytes]
Answer = Callable[[Any, str], list[Frames]]  # (request id, request kind) -> the messages to send back


def held_first(then: Callable[[Any, Any], list[Frames]]) -> Answer:
    """An answer that holds the first request's answer back until the second request arrives, and then
    sends ``then(first_id, second_id)``; nothing afterwards."""
    held: list[Any] = []

    def answer(rid: Any, kind: str) -> list[Frames]:
        if not held:
            held.append(rid)
            return []
        return then(held[0], rid)

    return answer


def good_reply(rid: Any) -> Frames:
    return [bytes(f) for f in encode(InferReply(id=rid, model="toy", actions=ACTIONS,
                                                timings=Timings(server_ms=1.0)))]


def reply_header(rid: Any, **changes: Any) -> dict[str, Any]:
    """A valid inline reply header for ``rid``; a change of None removes the field."""
    return changed({"v": 1, "kind": "reply", "id": rid, "model": "toy",
                    "actions": {"dtype": "float32", "shape": [2, 3], "data": ACTIONS.tobytes()},
                    "timings": {"queue_ms": 0.0, "server_ms": 1.0}}, changes)


def nested(n: int) -> list:
    v: list = []
    for _ in range(n):
        v = [v]
    return v


def framed(rid: Any, actions: dict[str, Any], *frames: bytes) -> Frames:
    return [pack_header(reply_header(rid, actions=actions)), *frames]


FRAME_REF = {"dtype": "float32", "shape": list(BIG_ACTIONS.shape), "frame": 1}

# Each builds, for the id of the request in flight, an answer whose header decodes and carries that id but
# that decode() refuses after the header, or that is no answer to an infer request; the text is what the
# error message must name.
MALFORMED: dict[str, tuple[Callable[[Any], Frames], str]] = {
    "array frame ref out of range": (lambda rid: framed(rid, {**FRAME_REF, "frame": 3}), "actions.frame"),
    "array frame too short": (lambda rid: framed(rid, FRAME_REF, BIG_ACTIONS.tobytes()[:100]), "needs 2048 bytes"),
    "array frame missing": (lambda rid: framed(rid, FRAME_REF), "actions.frame"),
    "extra frame": (lambda rid: [pack_header(reply_header(rid)), b"stray"], "array frames"),
    "bad dtype": (lambda rid: framed(rid, {"dtype": "complex128", "shape": [2, 3], "data": b"\0" * 96}),
                  "actions.dtype"),
    "bad shape": (lambda rid: framed(rid, {"dtype": "float32", "shape": [-1], "data": b""}), "actions.shape"),
    "array not a map": (lambda rid: framed(rid, [1, 2, 3]), "actions"),  # type: ignore[arg-type]
    "missing actions": (lambda rid: [pack_header(reply_header(rid, actions=None))], "actions: missing"),
    "bad timings": (lambda rid: [pack_header(reply_header(rid, timings="fast"))], "timings"),
    "bad timing value": (lambda rid: [pack_header(reply_header(rid, timings={"queue_ms": "x"}))], "timings"),
    "protocol version": (lambda rid: [pack_header(reply_header(rid, v=2))], "protocol version"),
    "missing kind": (lambda rid: [pack_header(reply_header(rid, kind=None))], "kind: missing"),
    "unknown kind": (lambda rid: [pack_header(reply_header(rid, kind="bogus"))], "bogus"),
    "error without code": (lambda rid: [pack_header({"v": 1, "kind": "error", "id": rid, "message": "x"})],
                           "code: missing"),
    # Valid messages, but not answers to an infer request: one used to vanish (pending no more, never
    # completed), the other to complete "ok" with no actions.
    "a request kind": (lambda rid: [pack_header({"v": 1, "kind": "ping", "id": rid})], "'ping'"),
    "a pong": (lambda rid: [bytes(f) for f in encode(Pong(id=rid))], "'pong'"),
    # repr() of a list nested a thousand deep raised RecursionError out of poll(), and the request waited out
    # its timeout
    "deeply nested version": (lambda rid: [pack_header(reply_header(rid, v=nested(1000)))], "protocol version"),
    "deeply nested dtype": (lambda rid: framed(rid, {"dtype": nested(1000), "shape": [2, 3], "data": b""}),
                            "actions.dtype"),
}

# Replies that carry no id of a request in flight here: there is nothing to fail, so they are dropped.
UNATTRIBUTABLE: dict[str, Callable[[Any], Frames]] = {
    "undecodable header": lambda rid: [b"\xc1\xc1 not msgpack", b"junk"],
    "truncated header": lambda rid: [pack_header(reply_header(rid))[:20]],
    "header not a map": lambda rid: [msgpack.packb([rid, "reply"])],
    "unknown id": lambda rid: good_reply(f"{rid}-other"),
    "unknown id, malformed body": lambda rid: framed(f"{rid}-other", {**FRAME_REF, "frame": 3}),
    "id of another type": lambda rid: [pack_header(reply_header(7))],  # the SDK's ids are strings
    "bool id": lambda rid: [pack_header(reply_header(True, actions=[1]))],
    "missing id": lambda rid: [pack_header(reply_header(rid, id=None, actions=[1]))],
}


class FakeRouter:
    """A ROUTER socket on loopback that answers each request with whatever ``answer`` returns.

    The socket lives in its own thread (ZeroMQ sockets are not thread-safe), so blocking SDK calls
    can be tested; ``answer`` can be swapped between requests.
    """

    def __init__(self, ctx: zmq.Context, answer: Answer):
        self.answer = answer
        self.requests: queue.Queue[tuple[Any, str]] = queue.Queue()
        self._stop = threading.Event()
        self._sock = ctx.socket(zmq.ROUTER)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.bind("tcp://127.0.0.1:*")
        self.address = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        try:
            while not self._stop.is_set():
                if not self._sock.poll(20):
                    continue
                robot, *body = self._sock.recv_multipart()
                msg = decode(body)
                kind = type(msg).__name__.lower()
                self.requests.put((msg.id, kind))
                for frames in self.answer(msg.id, kind):
                    self._sock.send_multipart([robot, *frames])
        finally:
            self._sock.close(linger=0)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)


@pytest.fixture
def serve():
    """serve(answer) -> (router, client); both are closed, and their context ended, after the test."""
    ctx = zmq.Context()
    made: list[tuple[FakeRouter, RobotClient]] = []

    def start(answer: Answer) -> tuple[FakeRouter, RobotClient]:
        router = FakeRouter(ctx, answer)
        made.append((router, RobotClient(router.address, robot_id="arm", timeout_s=TIMEOUT_S, context=ctx)))
        return made[-1]

    yield start
    for router, client in made:
        client.close()
        router.close()
    ctx.term()


def poll_until(client: RobotClient, within_s: float) -> list:
    got: list = []
    end = time.monotonic() + within_s
    while not got and time.monotonic() < end:
        got += client.poll(0.05)
    return got


def check_malformed(error: RobionError | None, rid: Any, why: str) -> None:
    assert isinstance(error, MalformedReply), error
    assert not isinstance(error, RequestTimeout)
    assert error.code == ErrorCode.INTERNAL
    assert error.request_id == rid
    assert error.message.startswith("malformed reply"), error.message
    assert why in error.message, error.message


@pytest.mark.parametrize("case", list(MALFORMED))
def test_a_malformed_reply_completes_its_request_at_once(serve, case):
    build, why = MALFORMED[case]
    router, c = serve(lambda rid, kind: [build(rid)])
    with c:
        t0 = time.monotonic()
        rid = c.submit("toy", IMAGES, STATE)
        got = poll_until(c, PROMPT_S)
        assert time.monotonic() - t0 < PROMPT_S, "the request waited for its timeout"
        assert [x.request_id for x in got] == [rid]
        done = got[0]
        assert not done.ok and done.actions is None and done.model == "toy" and done.reply_bytes > 0
        check_malformed(done.error, rid, why)
        assert c.pending() == 0 and c.poll(0.1) == []


@pytest.mark.parametrize("case", list(MALFORMED))
def test_infer_raises_at_once_on_a_malformed_reply(serve, case):
    build, why = MALFORMED[case]
    router, c = serve(lambda rid, kind: [build(rid)])
    with c:
        t0 = time.monotonic()
        with pytest.raises(RobionError) as e:
            c.infer("toy", IMAGES, STATE)
        assert time.monotonic() - t0 < PROMPT_S, "infer() waited for its timeout"
        rid, _ = router.requests.get(timeout=1)
        check_malformed(e.value, rid, why)
        assert c.pending() == 0
        router.answer = lambda rid, kind: [good_reply(rid)]
        done = c.infer("toy", IMAGES, STATE)  # and the client keeps working
        assert done.ok and np.array_equal(done.actions, ACTIONS)


INFINITE_STATE_DIM = {"cameras": ["cam0"], "image_shape": [8, 8, 3], "state_dim": float("inf"), "horizon": 2,
                      "action_dim": 3, "deadline_ms": 100.0}


@pytest.mark.parametrize("blocking", ["metadata", "metadata, infinite size", "ping"])
def test_a_blocking_round_trip_fails_at_once_on_a_malformed_answer(serve, blocking):
    """The infinite size used to escape decode() as OverflowError, out of metadata() and poll()."""
    broken = {"metadata": lambda rid: [pack_header({"v": 1, "kind": "metadata", "id": rid, "models": {"m": 5}})],
              "metadata, infinite size": lambda rid: [pack_header({"v": 1, "kind": "metadata", "id": rid,
                                                                    "models": {"m": INFINITE_STATE_DIM}})],
              "ping": lambda rid: [pack_header({"v": 1, "kind": "pong", "id": rid}), b"stray"]}[blocking]
    router, c = serve(lambda rid, kind: [broken(rid)])
    with c:
        call = c.ping if blocking == "ping" else c.metadata
        t0 = time.monotonic()
        with pytest.raises(MalformedReply) as e:
            call()
        assert time.monotonic() - t0 < PROMPT_S
        assert e.value.code == ErrorCode.INTERNAL and e.value.message.startswith("malformed reply")
        assert c.pending() == 0


def test_an_answer_of_the_wrong_kind_fails_its_request(serve):
    """A hello answered by an action chunk is as broken as garbage: it must not be taken for metadata."""
    router, c = serve(lambda rid, kind: [good_reply(rid)])
    with c:
        with pytest.raises(MalformedReply, match="'reply'"):
            c.metadata()
        info = ModelInfo(cameras=["cam0"], image_shape=[8, 8, 3], state_dim=4, horizon=2, action_dim=3,
                         deadline_ms=100.0)
        router.answer = lambda rid, kind: [[bytes(f) for f in encode(Metadata(id=rid, models={"toy": info}))]]
        assert c.metadata()["toy"] == info


@pytest.mark.parametrize("case", list(UNATTRIBUTABLE))
def test_an_unattributable_reply_is_dropped_and_the_client_keeps_working(serve, case):
    build = UNATTRIBUTABLE[case]
    # Each request is answered twice: first the reply that names no request here, then the good one.
    router, c = serve(lambda rid, kind: [build(rid), good_reply(rid)])
    with c:
        rid = c.submit("toy", IMAGES, STATE)
        got = poll_until(c, 2.0)
        got += c.poll(0.2)  # anything else that came: nothing must have been invented
        assert [(x.request_id, x.ok) for x in got] == [(rid, True)], [(x.request_id, x.error) for x in got]
        assert np.array_equal(got[0].actions, ACTIONS) and got[0].timings.server_ms == 1.0
        assert c.pending() == 0
        done = c.infer("toy", IMAGES, STATE)  # and the blocking path reads past it too
        assert done.ok and np.array_equal(done.actions, ACTIONS)


@pytest.mark.parametrize("case", list(UNATTRIBUTABLE))
def test_an_unattributable_reply_alone_leaves_its_request_to_time_out(serve, case):
    """With no good answer after it, the request is still in flight: nothing to fail, so the timeout decides.

    Once the client's timeout has passed, poll() reports it as RequestTimeout: it used to stay pending for ever.
    """
    build = UNATTRIBUTABLE[case]
    router, c = serve(lambda rid, kind: [build(rid)])
    with c:
        c.timeout_s = 1.5  # the client's timeout, read when poll() runs
        rid = c.submit("toy", IMAGES, STATE)
        assert c.poll(0.3) == []
        assert c.pending() == 1
        with pytest.raises(RequestTimeout):
            c.infer("toy", IMAGES, STATE, timeout_s=0.3)
        assert c.pending() == 1 and rid in c._pending  # infer's own request is not left behind
        got = poll_until(c, 3.0)
        assert [x.request_id for x in got] == [rid], "the request never timed out"
        assert isinstance(got[0].error, RequestTimeout) and got[0].error.code == ErrorCode.UNAVAILABLE
        assert c.pending() == 0 and c.poll(0.1) == []


def test_a_late_malformed_reply_after_a_timeout_is_not_a_new_completion(serve):
    """One outcome per request: once infer() raised RequestTimeout, a broken answer for it is dropped."""
    router, c = serve(held_first(lambda first, rid: [framed(first, {**FRAME_REF, "frame": 3}), good_reply(rid)]))
    with c:
        with pytest.raises(RequestTimeout):
            c.infer("toy", IMAGES, STATE, timeout_s=0.2)
        rid = c.submit("toy", IMAGES, STATE)
        got = poll_until(c, 2.0) + c.poll(0.2)
        assert [(x.request_id, x.ok) for x in got] == [(rid, True)]


def test_error_replies_are_still_the_servers_code(serve):
    """A well-formed error reply keeps its own code; only a broken answer becomes MalformedReply."""
    router, c = serve(lambda rid, kind: [[bytes(f) for f in encode(
        ErrorReply(id=rid, code=ErrorCode.OVERLOADED, message="queue full"))]])
    with c:
        with pytest.raises(RobionError) as e:
            c.infer("toy", IMAGES, STATE)
        assert e.value.code == ErrorCode.OVERLOADED and not isinstance(e.value, MalformedReply)
