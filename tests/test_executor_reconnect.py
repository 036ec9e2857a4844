"""A restarted router hears the executor's hello (with its instance) as soon as the executor reconnects.

The router tells a restarted executor from the hello's per-process instance token (tests/test_router_restart.py).
A router that itself restarted knows no instances: without a hello on reconnect it would learn this
executor's only at its next registration, and a later restart of the executor would look like a first
hello, so its requests in flight would wait out router.request_timeout_s.
"""

from __future__ import annotations

import time

import zmq

from shared import control
from tests.helpers import wait_until_bindable
from tests.test_executor_io import Harness


def hellos_until(sock: zmq.Socket, deadline: float, stop_at: dict | None = None) -> list[dict]:
    """The hellos ``sock`` receives until ``deadline``, or until one holds every field of ``stop_at``."""
    out: list[dict] = []
    while sock.poll(max(0, int((deadline - time.monotonic()) * 1000))):
        identity, _, frame = sock.recv_multipart()
        assert identity == b"ex0"
        out.append(control.unpack(frame))
        if (stop_at is not None and stop_at.items() <= out[-1].items()) or time.monotonic() >= deadline:
            break
    return out


def said(got: list[dict], expected: dict) -> bool:
    """Whether one of the hellos ``got`` holds every field of ``expected``."""
    return any(expected.items() <= hello.items() for hello in got)


def restart_router(h: Harness, away_s: float = 0.0) -> None:
    """The stand-in router process goes away (for ``away_s``) and a new one binds the same address."""
    h.router.close()
    time.sleep(away_s)
    router = h.ctx.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    wait_until_bindable(h.cfg.router.backend)  # the closed socket lets go of it in the background
    router.bind(h.cfg.router.backend)
    h.router = router


def test_the_executor_says_hello_again_to_a_restarted_router(tmp_path):
    h = Harness(tmp_path)
    try:
        hellos_until(h.router, time.monotonic() + 0.5)  # the start-up hellos (construction, registration)
        restart_router(h)
        router = h.router
        # on its second connection: the hellos of every heartbeat carry the first one's number
        expected = {"kind": "executor_hello", "executor": "ex0", "instance": h.io.instance, "connection": 2}
        got = hellos_until(router, time.monotonic() + 5.0, stop_at=expected)
        assert said(got, expected), got
        # The executor still serves through the new router.
        h.send(h.request("after-restart"))
        assert h.router.poll(10_000), "no reply through the restarted router"
    finally:
        h.close()
