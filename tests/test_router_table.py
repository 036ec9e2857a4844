"""A routing table the router cannot read: the current table is kept, and it is said once, without a traceback.

The router polls the control plane every TABLE_POLL_S; a control plane that keeps answering with a
malformed table must not fill the router's log with a traceback per poll. The router runs its real
loop in a thread (RouterThread); the control plane is a real ROUTER socket bound where the router's
control DEALER connects, answering every table_get.
"""

from __future__ import annotations

import logging
import threading
import time

import pytest
import zmq

from services.router import frontend
from services.router.frontend import TABLE_POLL_S
from shared import control
from shared.control import RoutingTable, TableError
from shared.protocol import Metadata, pack_header
from tests.test_router_robustness import INFO, RouterThread, ask, one_executor_table

GOOD = RoutingTable(version=2, models={"toy-a": INFO, "toy-b": INFO}, routes={"toy-a": ["ex0"], "toy-b": ["ex0"]},
                    executors=["ex0"])
MALFORMED = {
    "not a map": "v7",
    "no version": {"models": {}, "routes": {}},
    "version not a number": {**GOOD.to_wire(), "version": "seven"},
    "version infinite": {**GOOD.to_wire(), "version": float("inf")},
    "models a list": {**GOOD.to_wire(), "models": ["toy-a"]},
    "model description broken": {**GOOD.to_wire(), "models": {"toy-a": {"cameras": ["cam0"]}}},
    "quotas not numbers": {**GOOD.to_wire(), "quotas": {"toy-a": {"ex0": "many"}}},
}


class ControlPlane:
    """Answers every table_get with ``self.table`` (a wire dict, well-formed or not); counts the polls."""

    def __init__(self, ctx: zmq.Context, address: str, table):
        self.table = table
        self.polls = 0
        self.sock = ctx.socket(zmq.ROUTER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.bind(address)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.stop.is_set():
            if self.sock.poll(20):
                peer, frame = self.sock.recv_multipart()
                if control.unpack(frame).get("kind") == "table_get":
                    self.polls += 1
                    self.sock.send_multipart([peer, control.pack("table", table=self.table)])

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        self.sock.close(linger=0)


@pytest.mark.parametrize("case", list(MALFORMED))
def test_a_malformed_table_keeps_the_current_one_and_is_logged_once(tmp_path, caplog, monkeypatch, case):
    caplog.set_level(logging.INFO, logger="robion.router")
    monkeypatch.setattr(frontend, "WARN_EVERY_S", 60.0)  # one report for the whole test, however slow the host
    with RouterThread(tmp_path, one_executor_table()) as rt:
        cp = ControlPlane(rt.ctx, rt.cfg.control.bind, MALFORMED[case])
        try:
            end = time.monotonic() + 10
            while cp.polls < 10 and time.monotonic() < end:  # ten polls, ten malformed tables
                time.sleep(TABLE_POLL_S)
            assert cp.polls >= 10, f"the router polled {cp.polls} times"
            assert rt.router.routing.table == one_executor_table()  # the current table is kept
            # ... and served: the router is unharmed.
            meta = ask(rt.robot(b"arm"), [pack_header({"v": 1, "kind": "hello", "id": "h"})])
            assert isinstance(meta, Metadata) and set(meta.models) == {"toy-a"}

            # A well-formed table afterwards is applied as usual.
            cp.table = GOOD.to_wire()
            end = time.monotonic() + 5
            while rt.router.routing.table.version != GOOD.version and time.monotonic() < end:
                time.sleep(TABLE_POLL_S)
            assert rt.router.routing.table == GOOD
        finally:
            cp.close()
    warnings = [r for r in caplog.records if r.name == "robion.router" and r.levelno >= logging.WARNING]
    assert len(warnings) == 1, [r.getMessage() for r in warnings]  # rate-limited: not one per poll
    assert warnings[0].exc_info is None, "a traceback for what the control plane sent"
    assert "routing table" in warnings[0].getMessage()


@pytest.mark.parametrize("case", list(MALFORMED))
def test_from_wire_raises_table_error(case):
    """The one error the router catches: whatever is wrong with the table, from_wire raises TableError."""
    with pytest.raises(TableError):
        RoutingTable.from_wire(MALFORMED[case])


def test_from_wire_reads_what_to_wire_writes():
    assert RoutingTable.from_wire(GOOD.to_wire()) == GOOD
