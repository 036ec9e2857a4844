"""The fleet report counts a lost reply as NO_REPLY whenever it is found missing, and refuses a bad
--address or --seed with the option's name.

A stand-in router (a ROUTER socket speaking the real protocol, in a thread) describes one model, answers
the requests of robot 0 with UNAVAILABLE and never answers robot 1's: the router's UNAVAILABLE and a reply
that never came are different faults for an operator (retry vs. a lost message), so they must not share
a column.
"""

import subprocess
import sys
import threading
from pathlib import Path

import pytest
import zmq

from services.fleet.robots import run_fleet
from shared import protocol
from tests.helpers import TOY_INFO, cluster_config, free_ports

ROOT = Path(__file__).resolve().parent.parent


class HalfDeafRouter:
    def __init__(self, address: str):
        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.ROUTER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.bind(address)
        self.stop = threading.Event()
        self.answered = self.dropped = 0
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.stop.is_set():
            if not self.sock.poll(50):
                continue
            identity, *frames = self.sock.recv_multipart(copy=True)
            reply = self.answer(protocol.decode(frames))
            if reply is not None:
                self.sock.send_multipart([identity, *protocol.encode(reply)])

    def answer(self, msg):
        """The reply to ``msg``, or None to lose it."""
        if isinstance(msg, protocol.Hello):
            return protocol.Metadata(id=msg.id, models={"toy-a": protocol.ModelInfo.from_wire(TOY_INFO)})
        if msg.robot.endswith("-000"):  # robot 0 (by name: each client has a socket identity of its own)
            self.answered += 1
            return protocol.ErrorReply(id=msg.id, code=protocol.ErrorCode.UNAVAILABLE, message="no executor")
        self.dropped += 1  # robot 1: the reply is lost
        return None

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        self.sock.close()
        self.ctx.term()

    def __enter__(self) -> "HalfDeafRouter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def test_lost_replies_are_no_reply_also_after_the_client_timeout():
    (port,) = free_ports(1)
    with HalfDeafRouter(f"tcp://127.0.0.1:{port}") as router:
        # drain_s past the SDK's 10 s reply timeout: the lost replies surface as RequestTimeout in the
        # run, which the report counted as the router's UNAVAILABLE answers.
        report = run_fleet(f"tcp://127.0.0.1:{port}", robots=2, hz=4, duration_s=0.5, drain_s=12, network="none")
    r = report.models["toy-a"]
    assert router.answered > 0 and router.dropped > 0
    assert r.sent == router.answered + router.dropped and r.replies == 0 and r.slo_attainment == 0
    assert r.errors == {"UNAVAILABLE": router.answered, "NO_REPLY": router.dropped}, r.errors


@pytest.mark.parametrize("args, message", [(("--address", "router:5555"), "--address"),
                                           (("--seed", "-1"), "--seed")])
def test_bad_address_or_seed_is_a_usage_error(tmp_path, args, message):
    path, _ = cluster_config(tmp_path)
    res = subprocess.run([sys.executable, "-m", "services.fleet.main", "-c", str(path), "--duration", "0.5", *args],
                         capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert message in res.stderr, res.stderr


def test_json_report_of_a_model_with_no_replies_is_strict_json(tmp_path):
    """p50/p99 of a model with no successful reply are NaN, which json.dump writes as a bare NaN: not JSON
    (jq and JSON.parse refuse the file). They are written as null."""
    import json

    path, _ = cluster_config(tmp_path)
    (port,) = free_ports(1)
    out = tmp_path / "report.json"
    with HalfDeafRouter(f"tcp://127.0.0.1:{port}"):
        res = subprocess.run([sys.executable, "-m", "services.fleet.main", "-c", str(path), "--address",
                              f"tcp://127.0.0.1:{port}", "--robots", "2", "--duration", "0.5", "--json", str(out)],
                             capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert res.returncode == 0, res.stderr

    def refuse(constant):
        raise ValueError(f"not JSON: {constant}")

    report = json.loads(out.read_text(), parse_constant=refuse)
    r = report["models"]["toy-a"]
    assert r["replies"] == 0 and r["p50_ms"] is None and r["p99_ms"] is None and r["server_p50_ms"] is None


def test_a_report_that_cannot_be_written_leaves_the_previous_one_whole(tmp_path):
    """The file was opened for writing (truncated) first: a write that failed (here the file-size limit, as a full
    disk would) left the previous report cut short, invalid JSON, and ended the run with a traceback."""
    import json
    import resource

    path, _ = cluster_config(tmp_path)
    (port,) = free_ports(1)
    out = tmp_path / "report.json"
    previous = json.dumps({"previous": "x" * 2000})
    out.write_text(previous)

    def small_files() -> None:  # Python ignores SIGXFSZ: a write past the limit fails with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (200, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))

    with HalfDeafRouter(f"tcp://127.0.0.1:{port}"):
        res = subprocess.run([sys.executable, "-m", "services.fleet.main", "-c", str(path), "--address",
                              f"tcp://127.0.0.1:{port}", "--robots", "2", "--duration", "0.5", "--json", str(out)],
                             capture_output=True, text=True, cwd=ROOT, timeout=60, preexec_fn=small_files)
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr[-2000:]
    assert "--json: cannot write" in res.stderr and "toy-a" in res.stdout  # the table still came out
    assert out.read_text() == previous


class TwoModelRouter(HalfDeafRouter):
    """Describes toy-a (answered UNAVAILABLE) and toy-wide, whose 1025 cameras no request can carry (the SDK
    refuses to send one), and a third model no robot is spread to."""

    def answer(self, msg):
        if isinstance(msg, protocol.Hello):
            wide = {**TOY_INFO, "cameras": [f"c{i}" for i in range(1025)], "image_shape": [1, 1, 3]}
            return protocol.Metadata(id=msg.id, models={
                "toy-a": protocol.ModelInfo.from_wire(TOY_INFO), "toy-wide": protocol.ModelInfo.from_wire(wide),
                "toy-z": protocol.ModelInfo.from_wire(TOY_INFO)})
        self.answered += 1
        return protocol.ErrorReply(id=msg.id, code=protocol.ErrorCode.UNAVAILABLE, message="no executor")


def test_a_request_that_cannot_be_sent_fails_alone_and_idle_models_are_not_reported():
    """A submit that raised (a request the SDK refuses to send, or a send queue full with the router gone)
    ended the whole run with no report; it is now that request's failure. A model no robot was spread to
    (fewer robots than models) was reported at 0% SLO attainment for requests never sent."""
    (port,) = free_ports(1)
    with TwoModelRouter(f"tcp://127.0.0.1:{port}") as router:
        report = run_fleet(f"tcp://127.0.0.1:{port}", robots=2, hz=4, duration_s=0.5, network="none",
                           models=["toy-a", "toy-wide", "toy-z"])
    assert set(report.models) == {"toy-a", "toy-wide"}
    a, wide = report.models["toy-a"], report.models["toy-wide"]
    assert a.sent == router.answered > 0 and a.errors == {"UNAVAILABLE": a.sent}
    assert wide.sent > 0 and wide.replies == 0 and wide.errors == {"BAD_REQUEST": wide.sent}, wide.errors
    assert wide.slo_attainment == 0


def test_latency_counts_from_the_scheduled_send_and_a_late_sender_is_reported(tmp_path, monkeypatch):
    """A host too slow for its fleet sends late. Latency was timed from the actual send, so that lag was in no number
    and the report looked healthy; it counts from the robot's schedule now, and the report says how late it sent."""
    import time

    import numpy as np

    from shared.client import RobotClient

    class Answering(HalfDeafRouter):
        def answer(self, msg):
            if isinstance(msg, protocol.Hello):
                return super().answer(msg)
            info = protocol.ModelInfo.from_wire(TOY_INFO)
            return protocol.InferReply(id=msg.id, model=msg.model,
                                       actions=np.zeros((info.horizon, info.action_dim), np.float32))

    submit = RobotClient.submit

    def slow_submit(self, *args, **kwargs):
        time.sleep(0.03)  # 4 robots at 10 Hz need a send every 25 ms
        return submit(self, *args, **kwargs)

    monkeypatch.setattr(RobotClient, "submit", slow_submit)
    (port,) = free_ports(1)
    with Answering(f"tcp://127.0.0.1:{port}"):
        report = run_fleet(f"tcp://127.0.0.1:{port}", robots=4, hz=10, duration_s=1.0, network="none")
    r = report.models["toy-a"]
    assert r.replies == r.sent > 0 and r.send_lag_max_ms > 50
    assert r.p99_ms >= r.send_lag_p99_ms  # each request's latency includes how late it left
    assert "this host sent requests up to" in report.table()
    assert report.to_dict()["models"]["toy-a"]["send_lag_max_ms"] == r.send_lag_max_ms


def test_a_fleet_of_more_robots_than_a_default_zmq_context_allows_runs():
    """The fleet used ZeroMQ's shared context, which allows 1023 sockets: --robots 1100 ended in a ZMQError
    traceback ("Too many open files"). It now has a context of its own, sized for its robots."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    need = 8192  # both ends of 1100 connections in this process, and ZeroMQ's own descriptors
    if hard != resource.RLIM_INFINITY and hard < need:
        pytest.skip(f"the open-files limit of this host is {hard}")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, need), hard))
    (port,) = free_ports(1)
    try:
        with HalfDeafRouter(f"tcp://127.0.0.1:{port}"):
            report = run_fleet(f"tcp://127.0.0.1:{port}", robots=1100, hz=1, duration_s=1.0, drain_s=0.5,
                               network="none")
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    r = report.models["toy-a"]
    assert r.robots == 1100 and r.sent == 1100
    # Robot 0's one request is answered UNAVAILABLE, the rest are lost by this router. A request whose robot was not
    # connected yet when it was due was UNAVAILABLE too: the fleet's clock now starts once every robot is connected.
    assert r.errors == {"UNAVAILABLE": 1, "NO_REPLY": 1099}, r.errors


def test_robots_are_all_connected_before_the_clock_starts_or_the_fleet_says_it_could_not():
    from services.fleet.robots import _connect_all
    from shared.client import RobotClient

    (port, unused) = free_ports(2)
    ctx = zmq.Context()
    try:
        with HalfDeafRouter(f"tcp://127.0.0.1:{port}"):
            clients = [RobotClient(f"tcp://127.0.0.1:{p}", context=ctx) for p in (port, port, unused)]
            try:
                assert _connect_all(clients, 0.5) == 1  # nothing listens on the third's port
                assert _connect_all(clients[:2], 0.5) == 0
            finally:
                for c in clients:
                    c.close()
    finally:
        ctx.term()


def test_an_atomic_write_follows_a_symlink_and_streams_into_a_pipe(tmp_path):
    """The report's rename replaced a symlink with a file (its target kept the old report), and failed for a shell's
    `--json >(jq .)` (/dev/fd/N, where no temp file can be made beside it)."""
    import os

    from shared.files import write_atomic

    target = tmp_path / "reports" / "latest.json"
    target.parent.mkdir()
    target.write_text("{}")
    link = tmp_path / "report.json"
    link.symlink_to(target)
    write_atomic(link, '{"new": 1}')
    assert link.is_symlink() and target.read_text() == '{"new": 1}'
    read, write = os.pipe()
    try:
        write_atomic(f"/dev/fd/{write}", "streamed")
        os.close(write)
        write = -1
        assert os.read(read, 100) == b"streamed"
    finally:
        os.close(read)
        if write >= 0:
            os.close(write)
