"""The robot SDK's submitted requests expire: each gets exactly one outcome, a reply or RequestTimeout.

A request sent with ``submit()`` whose reply never comes (the router died, or the reply's header could
not be decoded and was dropped) used to stay pending forever: ``pending()`` never reached 0 and
``poll()`` never reported it. ``poll()`` (and ``wait_any``) now complete it with RequestTimeout once it
is older than the client's ``timeout_s``; a reply arriving after that is dropped.

A bare ZeroMQ ROUTER socket in a thread plays the router (tests/test_client_garbled.py's FakeRouter).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest
import zmq

from shared.client import RequestTimeout, RobionError, RobotClient, wait_any
from shared.protocol import ErrorCode
from tests.test_client_garbled import (ACTIONS, IMAGES, STATE, UNATTRIBUTABLE, Answer, FakeRouter, Frames, good_reply,
                                       held_first, poll_until)

TIMEOUT_S = 0.3
SLACK_S = 1.0  # scheduling slack on a busy host: an expiry must come within TIMEOUT_S + SLACK_S


def silent(rid: Any, kind: str) -> list[Frames]:
    return []


@pytest.fixture
def serve():
    """serve(answer, timeout_s) -> (router, client); closed, and their context ended, after the test."""
    ctx = zmq.Context()
    made: list[Any] = []

    def start(answer: Answer, timeout_s: float = TIMEOUT_S, router: FakeRouter | None = None):
        if router is None:
            router = FakeRouter(ctx, answer)
            made.append(router)
        client = RobotClient(router.address, robot_id=f"arm-{len(made)}", timeout_s=timeout_s, context=ctx)
        made.append(client)
        return router, client

    yield start
    for thing in reversed(made):
        thing.close()
    ctx.term()


def check_timeout(done, rid: str, timeout_s: float = TIMEOUT_S) -> None:
    assert done.request_id == rid and not done.ok and done.actions is None
    assert isinstance(done.error, RequestTimeout) and isinstance(done.error, RobionError)
    assert done.error.code == ErrorCode.UNAVAILABLE and done.error.request_id == rid
    assert done.latency_s >= timeout_s
    assert done.model == "toy" and done.request_bytes > 0 and done.reply_bytes == 0


def test_a_submitted_request_with_no_reply_times_out_in_poll(serve):
    router, c = serve(silent)
    rid = c.submit("toy", IMAGES, STATE)
    assert c.poll(0) == [] and c.pending() == 1  # not yet: its timeout has not passed
    t0 = time.monotonic()
    got = poll_until(c, TIMEOUT_S + SLACK_S)
    assert [x.request_id for x in got] == [rid], "the request never expired"
    check_timeout(got[0], rid)
    assert time.monotonic() - t0 < TIMEOUT_S + SLACK_S
    assert c.pending() == 0
    assert c.poll(0.2) == []  # one outcome: it is not reported again


def test_poll_returns_at_an_expiry_rather_than_at_its_own_timeout(serve):
    router, c = serve(silent)
    rid = c.submit("toy", IMAGES, STATE)
    t0 = time.monotonic()
    got = c.poll(10.0)
    assert time.monotonic() - t0 < TIMEOUT_S + SLACK_S, "poll() waited past the request's expiry"
    assert [x.request_id for x in got] == [rid]
    check_timeout(got[0], rid)


def test_pending_reaches_zero_when_no_reply_ever_comes(serve):
    """The documented drain loop, ``while client.pending(): client.poll(...)``, ends."""
    router, c = serve(silent)
    ids = {c.submit("toy", IMAGES, STATE) for _ in range(3)}
    got = []
    end = time.monotonic() + TIMEOUT_S + SLACK_S
    while c.pending() and time.monotonic() < end:
        got += c.poll(0.05)
    assert c.pending() == 0
    assert sorted(x.request_id for x in got) == sorted(ids)
    for done in got:
        check_timeout(done, done.request_id)


def test_answered_requests_complete_and_unanswered_ones_expire_each_once(serve):
    router, c = serve(lambda rid, kind: [good_reply(rid)] if int(rid.rsplit("-", 1)[1]) % 2 == 0 else [])
    ids = [c.submit("toy", IMAGES, STATE) for _ in range(6)]
    got = []
    end = time.monotonic() + TIMEOUT_S + SLACK_S
    while c.pending() and time.monotonic() < end:
        got += c.poll(0.05)
    by_id = {x.request_id: x for x in got}
    assert len(got) == len(by_id) == 6 and set(by_id) == set(ids)
    for i, rid in enumerate(ids):
        if i % 2 == 0:
            assert by_id[rid].ok and np.array_equal(by_id[rid].actions, ACTIONS)
        else:
            check_timeout(by_id[rid], rid)


def test_a_reply_after_the_expiry_is_dropped(serve):
    router, c = serve(held_first(lambda first, rid: [good_reply(first), good_reply(rid)]))
    first = c.submit("toy", IMAGES, STATE)
    got = poll_until(c, TIMEOUT_S + SLACK_S)
    assert [x.request_id for x in got] == [first]
    check_timeout(got[0], first)
    second = c.submit("toy", IMAGES, STATE)
    got = poll_until(c, SLACK_S) + c.poll(0.2)
    assert [(x.request_id, x.ok) for x in got] == [(second, True)], [(x.request_id, x.error) for x in got]
    assert c.pending() == 0


def test_the_timeout_is_the_clients_at_poll_time_and_counts_from_the_send(serve):
    router, c = serve(silent, timeout_s=30.0)
    rid = c.submit("toy", IMAGES, STATE)
    time.sleep(0.1)
    assert c.poll(0) == []
    c.timeout_s = 0.05  # already older than that
    got = c.poll(0)
    assert [x.request_id for x in got] == [rid]
    check_timeout(got[0], rid, 0.05)
    assert "0.050 s" in got[0].error.message


def test_a_request_expiring_during_a_blocking_call_is_reported_by_the_next_poll(serve):
    router, c = serve(silent)
    rid = c.submit("toy", IMAGES, STATE)
    with pytest.raises(RequestTimeout):
        c.ping(timeout_s=TIMEOUT_S + 0.1)  # the router answers nothing
    assert c.pending() == 1  # the ping is not pending: its caller got its outcome
    got = c.poll(0)
    assert [x.request_id for x in got] == [rid]
    check_timeout(got[0], rid)
    assert c.pending() == 0


def test_wait_any_surfaces_expirations(serve):
    router, quiet = serve(silent)
    _, idle = serve(silent, router=router)  # nothing submitted: must not hold wait_any up or report anything
    rid = quiet.submit("toy", IMAGES, STATE)
    t0 = time.monotonic()
    got = []
    while not got and time.monotonic() - t0 < TIMEOUT_S + SLACK_S:
        got = wait_any([idle, quiet], 10.0)
    assert time.monotonic() - t0 < TIMEOUT_S + SLACK_S, "wait_any() waited past the request's expiry"
    assert [(client, x.request_id) for client, x in got] == [(quiet, rid)]
    check_timeout(got[0][1], rid)
    assert quiet.pending() == 0 and idle.pending() == 0


@pytest.mark.parametrize("case", ["undecodable header", "truncated header", "unknown id"])
def test_a_request_whose_only_reply_is_unattributable_times_out_in_poll(serve, case):
    router, c = serve(lambda rid, kind: [UNATTRIBUTABLE[case](rid)])
    rid = c.submit("toy", IMAGES, STATE)
    got = poll_until(c, TIMEOUT_S + SLACK_S)
    assert [x.request_id for x in got] == [rid]
    check_timeout(got[0], rid)
    assert c.pending() == 0
