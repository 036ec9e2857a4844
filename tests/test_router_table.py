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
from tests.helpers import changed
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
    # A str is iterable: read as a list it used to route toy-a to executors "e", "x" and "0".
    "route a string": {**GOOD.to_wire(), "routes": {"toy-a": "ex0", "toy-b": ["ex0"]}},
}

FULL = RoutingTable(version=3, models={"toy-a": INFO, "toy-b": INFO}, routes={"toy-a": ["ex0", "ex1"], "toy-b": []},
                    quotas={"toy-a": {"ex0": 3, "ex1": 2}}, limits={"toy-a": 4}, executors=["ex0", "ex1", "ex2"])

# Tables of the wrong shape that conversions used to accept (int("7"), int(2.9), list("ex0"), str(1)), and the
# field the TableError must name.
WRONG_SHAPE = {
    "route a string": ({"routes": {"toy-a": "ex0", "toy-b": []}}, "routes['toy-a']"),
    "route a map": ({"routes": {"toy-a": {"ex0": 1}, "toy-b": []}}, "routes['toy-a']"),
    "route entry not a string": ({"routes": {"toy-a": ["ex0", 1], "toy-b": []}}, "routes['toy-a']"),
    "routes not a map": ({"routes": [["toy-a", ["ex0"]]]}, "routes"),
    "model name not a string": ({"routes": {1: ["ex0"]}}, "routes"),
    "version a numeric string": ({"version": "7"}, "version"),
    "version a float": ({"version": 2.9}, "version"),
    "version a whole float": ({"version": 3.0}, "version"),
    "version a bool": ({"version": True}, "version"),
    "version missing": ({"version": None}, "version"),
    "quotas not a map": ({"quotas": [1, 2]}, "quotas"),
    "quota not a map": ({"quotas": {"toy-a": 5}}, "quotas['toy-a']"),
    "quota a float": ({"quotas": {"toy-a": {"ex0": 1.5}}}, "quotas['toy-a']['ex0']"),
    "quota a numeric string": ({"quotas": {"toy-a": {"ex0": "3"}}}, "quotas['toy-a']['ex0']"),
    "quota a bool": ({"quotas": {"toy-a": {"ex0": True}}}, "quotas['toy-a']['ex0']"),
    "quota executor not a string": ({"quotas": {"toy-a": {0: 3}}}, "quotas['toy-a']"),
    "limits not a map": ({"limits": 4}, "limits"),
    "limit a float": ({"limits": {"toy-a": 4.5}}, "limits['toy-a']"),
    "limit a numeric string": ({"limits": {"toy-a": "4"}}, "limits['toy-a']"),
    "executors a string": ({"executors": "ex0"}, "executors"),
    "executors a map": ({"executors": {"ex0": 1}}, "executors"),
    "executor not a string": ({"executors": ["ex0", 1]}, "executors"),
    "models not a map": ({"models": ["toy-a"]}, "models"),
}


def wrong(changes: dict) -> dict:
    """FULL's wire form with ``changes``; a change of None removes the field."""
    return changed(FULL.to_wire(), changes)


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
    assert RoutingTable.from_wire(FULL.to_wire()) == FULL
    # ... and what reaches the router: the table message through msgpack.
    assert RoutingTable.from_wire(control.unpack(control.pack("table", table=FULL.to_wire()))["table"]) == FULL


def test_from_wire_takes_tuples_for_lists_and_defaults_the_optional_fields():
    d = {**FULL.to_wire(), "routes": {"toy-a": ("ex0", "ex1"), "toy-b": ()}, "executors": ("ex0", "ex1", "ex2")}
    assert RoutingTable.from_wire(d) == FULL
    bare = {k: v for k, v in FULL.to_wire().items() if k not in ("quotas", "limits", "executors")}
    assert RoutingTable.from_wire(bare) == RoutingTable(version=3, models=FULL.models, routes=FULL.routes)


@pytest.mark.parametrize("case", list(WRONG_SHAPE))
def test_from_wire_refuses_a_wrong_shape_and_names_the_field(case):
    changes, field_name = WRONG_SHAPE[case]
    with pytest.raises(TableError) as e:
        RoutingTable.from_wire(wrong(changes))
    assert field_name in str(e.value), str(e.value)


def test_one_table_poll_is_outstanding_while_the_control_plane_is_busy(tmp_path):
    """The router polled every TABLE_POLL_S whether or not the last poll was answered. While the control plane solved
    (seconds: it reads nothing meanwhile) about ten polls a second piled up; it then answered each with the whole new
    table, and the router decoded them all while robots' requests waited (a ping took 0.36 s after a 5 s solve with a
    64-GPU table in a reviewer's run, 1.7 s with a larger one). Now one poll is outstanding, sent again each
    TABLE_POLL_RETRY_S, and an answered poll is followed by the next one within a poll interval."""
    with RouterThread(tmp_path, one_executor_table()) as rt:
        plane = rt.ctx.socket(zmq.ROUTER)  # a control plane busy solving: it reads nothing for 2.5 s
        plane.setsockopt(zmq.LINGER, 0)
        plane.bind(rt.cfg.control.bind)
        rt.socks.append(plane)
        time.sleep(2.5)
        polls = []
        while plane.poll(100):
            polls.append(plane.recv_multipart())
        assert 1 <= len(polls) <= 2 + 2.5 / frontend.TABLE_POLL_RETRY_S, len(polls)
        peer = polls[-1][0]
        plane.send_multipart([peer, control.pack("table", table=None)])  # answered: nothing newer
        t0 = time.monotonic()
        assert plane.poll(2000), "no poll after the answer"
        assert time.monotonic() - t0 < 0.5
        assert control.unpack(plane.recv_multipart()[-1])["kind"] == "table_get"
