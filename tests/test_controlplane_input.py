"""The control plane answers bad input with a clear error and keeps serving.

A real control plane runs on a loopback socket in a thread; executors and routers are stood in
for by the messages the real ones send (shared/control.py), with one field broken at a time.
"""

import math
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import yaml

from shared.cluster import control_request, control_status
from tests.helpers import TOY_INFO, cluster_config, free_ports, start_control_plane, wait_for

ROOT = Path(__file__).resolve().parent.parent
INFO = TOY_INFO
# Short enough that a missing reply fails fast; a reply from a loopback plane takes milliseconds.
WAIT_S = 2.0


@pytest.fixture
def plane(tmp_path):
    """A real control plane whose models have populations but no configured limits (measured ones count)."""
    path, data = cluster_config(tmp_path)
    for m, robots in zip(data["models"], (4, 2)):
        m["robots"] = robots
    cfg, stop, t = start_control_plane(path, data)
    yield cfg.control.bind, path, data, t
    stop.set()
    t.join(10)


def request(address: str, kind: str, **fields) -> dict | None:
    return control_request(address, kind, timeout_s=WAIT_S, **fields)


def settled_table(address: str) -> dict:
    """The plane's answer to a router's table_get once it offers a table: ex1, configured, never registers
    here, so a just-started plane holds its table for its first few heartbeat intervals."""
    replies: list = []
    assert wait_for(lambda: replies.append(request(address, "table_get", version=-1, role="router"))
                    or (replies[-1] or {}).get("table") is not None, WAIT_S), replies[-1]
    return replies[-1]


def assert_bad_request(reply: dict | None, field: str) -> None:
    assert reply is not None, "no reply: the sender waited until its timeout"
    assert reply["kind"] == "error" and reply["code"] == "BAD_REQUEST", reply
    assert field in reply["message"], reply


# ----------------------------------------------------------------- A: timeouts


@pytest.mark.parametrize("timeout_s", [-1.0, 0.0, math.nan, math.inf])
def test_control_request_refuses_a_timeout_that_is_not_positive_and_finite(timeout_s):
    """A negative timeout made poll() wait forever; zero never waited for an answer at all."""
    (port,) = free_ports(1)  # nothing listens there: the request can only end by its timeout
    outcome: list = []

    def call():
        try:
            outcome.append(control_request(f"tcp://127.0.0.1:{port}", "status", timeout_s=timeout_s))
        except Exception as exc:
            outcome.append(exc)

    t = threading.Thread(target=call, daemon=True)
    t.start()
    t.join(WAIT_S)
    assert not t.is_alive(), f"control_request(timeout_s={timeout_s}) is still waiting"
    assert isinstance(outcome[0], ValueError) and "timeout_s" in str(outcome[0]), outcome


@pytest.mark.parametrize("value", ["-1", "0", "nan"])
def test_ctl_refuses_a_timeout_that_is_not_positive(plane, value):
    address, path, data, _ = plane
    res = subprocess.run([sys.executable, "-m", "shared.cli", "ctl", "status", "-c", str(path), "--timeout", value],
                         capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    assert "--timeout" in res.stderr and "positive" in res.stderr, res.stderr
    assert "Traceback" not in res.stderr, res.stderr


# ----------------------------------------------------------------- B: malformed messages


REGISTER = {"executor": "ex0", "device": "cpu", "models": {"toy-a": INFO}}


@pytest.mark.parametrize("kind, fields, field", [
    ("register", {k: v for k, v in REGISTER.items() if k != "executor"}, "executor"),
    ("register", {**REGISTER, "executor": 7}, "executor"),
    ("register", {k: v for k, v in REGISTER.items() if k != "models"}, "models"),
    ("register", {**REGISTER, "models": ["toy-a"]}, "models"),
    ("register", {**REGISTER, "models": {"toy-a": {"cameras": ["cam0"]}}}, "models"),
    ("register", {**REGISTER, "models": {"toy-a": {**INFO, "state_dim": "four"}}}, "models"),
    ("register", {**REGISTER, "models": {"toy-a": {**INFO, "state_dim": float("inf")}}}, "models"),
    ("register", {**REGISTER, "limits": ["toy-a", 4]}, "limits"),
    ("table_get", {"role": "router", "version": "3"}, "version"),
    ("table_get", {"role": "router", "version": 2.5}, "version"),
    ("table_get", {"role": "router", "version": None}, "version"),
    ("heartbeat", {}, "executor"),
    ("heartbeat", {"executor": "ex0", "depths": [1, 2]}, "depths"),
    ("heartbeat", {"executor": "ex0", "depths": {"toy-a": [[[1]]]}}, "depths"),
    ("heartbeat", {"executor": "ex0", "depths": {"toy-a": -1}}, "depths"),
    ("heartbeat", {"executor": "ex0", "depths": {"toy-a": True}}, "depths"),
    ("deregister", {}, "executor"),
    ("deregister", {"executor": ["ex0"]}, "executor"),
], ids=["register-no-executor", "register-executor-not-str", "register-no-models", "register-models-not-map",
        "register-model-info-incomplete", "register-model-info-mistyped", "register-model-info-infinite",
        "register-limits-not-map",
        "table_get-version-str", "table_get-version-float", "table_get-version-null", "heartbeat-no-executor",
        "heartbeat-depths-not-map", "heartbeat-depth-nested", "heartbeat-depth-negative", "heartbeat-depth-bool",
        "deregister-no-executor", "deregister-executor-not-str"])
def test_malformed_control_message_is_answered_bad_request(plane, kind, fields, field):
    address, _, _, t = plane
    assert_bad_request(request(address, kind, **fields), field)
    # Nothing was half-done, and the plane still serves well-formed messages.
    status = control_status(address, WAIT_S)
    assert status is not None and status["executors"] == {} and status["router"]["version"] == -1
    assert request(address, "register", **REGISTER)["kind"] == "registered"
    assert t.is_alive()


def test_well_formed_control_messages_are_answered_as_before(plane):
    """What the real executor and router send: only register and table_get are answered (and an unknown heartbeat)."""
    address, _, _, _ = plane
    assert request(address, "heartbeat", executor="ex0", depths={}) == {"kind": "reregister"}
    reply = request(address, "register", **REGISTER, limits={"toy-a": 4})
    assert reply == {"kind": "registered", "version": reply["version"]}
    assert control_request(address, "heartbeat", timeout_s=0.3, executor="ex0", depths={"toy-a": 0}) is None
    table = settled_table(address)
    assert table["kind"] == "table" and table["table"]["version"] == reply["version"]
    assert request(address, "table_get", version=reply["version"], role="router") == {"kind": "table", "table": None}
    assert control_request(address, "deregister", timeout_s=0.3, executor="ex0") is None
    assert control_status(address, WAIT_S)["executors"] == {}


def test_admin_errors_carry_a_code(plane, tmp_path):
    address, _, data, _ = plane
    reply = request(address, "drain", executor="nope")
    assert reply["kind"] == "error" and reply["code"] == "UNKNOWN_EXECUTOR" and "nope" in reply["message"], reply
    reply = request(address, "apply", config="models: [")
    assert reply["kind"] == "error" and reply["code"] == "BAD_CONFIG" and "YAML at line 1" in reply["message"], reply
    reply = request(address, "apply", config=yaml.safe_dump({**data, "engine": {"kind": "monolithic", "max_batch": 4}}))
    assert reply["kind"] == "error" and reply["code"] == "RESTART_REQUIRED" and "max_batch" in reply["message"], reply
    assert "control.headroom" in reply["message"] and "memory_gb" in reply["message"], reply  # what is live
    # A change of imports is refused before the modules are imported: their code never runs in the plane (this one
    # would write a file, and one that exits at import ended the plane).
    marker = tmp_path / "imported"
    (tmp_path / "side_effect_mod.py").write_text(f"open({str(marker)!r}, 'w').close()\n")
    sys.path.insert(0, str(tmp_path))
    try:
        reply = request(address, "apply", config=yaml.safe_dump({**data, "imports": ["side_effect_mod"]}))
    finally:
        sys.path.remove(str(tmp_path))
    assert reply["kind"] == "error" and reply["code"] == "RESTART_REQUIRED" and "imports" in reply["message"], reply
    assert not marker.exists()
    reply = request(address, "apply", config=yaml.safe_dump({**data, "imports": [5]}))  # malformed: not a restart
    assert reply["kind"] == "error" and reply["code"] == "BAD_CONFIG" and "imports[0]" in reply["message"], reply
    reply = request(address, "nonsense")
    assert reply["kind"] == "error" and reply["code"] == "BAD_REQUEST" and "nonsense" in reply["message"], reply


# ----------------------------------------------------------------- C: robot limits


@pytest.mark.parametrize("bad", [0, -3, 2.5, math.inf, math.nan, True, "4"],
                         ids=["zero", "negative", "fraction", "inf", "nan", "bool", "str"])
def test_invalid_measured_limits_are_ignored_and_valid_ones_kept(plane, bad):
    address, _, data, t = plane
    population = {m["name"]: m["robots"] for m in data["models"]}
    both = {"toy-a": INFO, "toy-b": INFO}
    reply = request(address, "register", executor="ex0", device="cpu", models=both, limits={"toy-b": 4})
    assert reply is not None and reply["kind"] == "registered", reply
    # ex1 reports a bad limit for toy-b next to a valid one for toy-a, in the same message.
    reply = request(address, "register", executor="ex1", device="cpu", models=both, limits={"toy-a": 4, "toy-b": bad})
    assert reply is not None and reply["kind"] == "registered", reply
    status = control_status(address, WAIT_S)
    assert status["limits"] == {"toy-a": 4, "toy-b": 4}
    table = status["table"]
    assert table["limits"] == {"toy-a": 4, "toy-b": 4}
    assert {m: sum(q.values()) for m, q in table["quotas"].items()} == population, table["quotas"]
    assert t.is_alive()


# ----------------------------------------------------------------- D: apply's config field


@pytest.mark.parametrize("fields", [{}, {"config": None}, {"config": 7}, {"config": {"models": []}}],
                         ids=["missing", "null", "int", "map"])
def test_apply_without_a_config_text_is_answered_bad_request(plane, fields):
    """A missing or mistyped `config` was turned into text by str() and parsed as YAML ("None", "7"):
    answered BAD_CONFIG `config: expected a mapping`, as if the operator's file were wrong."""
    address, _, _, t = plane
    before = control_status(address, WAIT_S)["table"]["version"]
    assert_bad_request(request(address, "apply", **fields), "config")
    status = control_status(address, WAIT_S)
    assert status["table"]["version"] == before and status["rollout"] is None
    assert t.is_alive()


def test_apply_of_deeply_nested_yaml_is_answered_bad_config(plane):
    """PyYAML builds nested collections recursively: a file of 20000 '[' raised RecursionError, which was
    answered INTERNAL ("see the control plane's log") instead of naming the file as the problem."""
    address, _, _, t = plane
    reply = control_request(address, "apply", timeout_s=10, config="[" * 20000)  # the parse takes seconds on a busy host
    assert reply is not None and reply["kind"] == "error" and reply["code"] == "BAD_CONFIG", reply
    assert "YAML" in reply["message"], reply
    assert control_status(address, WAIT_S)["rollout"] is None and t.is_alive()


# ----------------------------------------------------------------- E: values the wire cannot carry back


def test_apply_of_a_limit_msgpack_cannot_pack_is_refused_and_tables_still_served(plane):
    """A limit of 2**64 loaded and was installed: from then on every table_get and status failed to pack
    their reply and went unanswered (routers never got a table again)."""
    address, _, data, t = plane
    new = yaml.safe_load(yaml.safe_dump(data))
    new["models"][0]["limit"] = 2 ** 64
    reply = request(address, "apply", config=yaml.safe_dump(new))
    assert reply is not None and reply["kind"] == "error" and reply["code"] == "BAD_CONFIG", reply
    assert "models[0].limit" in reply["message"], reply
    assert settled_table(address)["kind"] == "table"
    assert control_status(address, WAIT_S) is not None and t.is_alive()


@pytest.mark.parametrize("field, value", [("state_dim", 1e30), ("horizon", "1" * 30), ("action_dim", -1e25)])
def test_a_model_description_that_cannot_be_sent_on_is_answered_bad_request(plane, field, value):
    """int(1e30) is an integer msgpack cannot pack: the description was kept (it outlives its executor), and
    every table_get and status after it failed without a reply, for every router, until a restart."""
    address, _, _, t = plane
    bad = {**REGISTER, "executor": "ex1", "models": {"toy-a": {**INFO, field: value}}}
    assert_bad_request(request(address, "register", **bad), "models.toy-a")
    assert settled_table(address)["kind"] == "table"
    status = control_status(address, WAIT_S)
    assert status is not None and status["executors"] == {}
    assert request(address, "register", **REGISTER)["kind"] == "registered"
    assert t.is_alive()


def test_an_unforeseen_failure_of_an_answered_message_is_answered_internal(plane, monkeypatch):
    """register, table_get and status expect a reply: an unforeseen failure was only logged, and the sender
    waited out its timeout with no idea why."""
    import services.controlplane.state as state

    address, _, _, t = plane

    def broken(*args, **kwargs):
        raise RuntimeError("status exploded")

    monkeypatch.setattr(state.ClusterState, "status", broken)
    reply = request(address, "status")
    assert reply is not None and reply["kind"] == "error" and reply["code"] == "INTERNAL", reply
    assert "status exploded" in reply["message"], reply
    monkeypatch.undo()
    assert control_status(address, WAIT_S) is not None and t.is_alive()


def test_messages_nested_a_thousand_deep_are_answered_and_status_keeps_working(plane):
    """An unknown kind nested 1000 deep: quoting it with repr() raised RecursionError and the sender got no answer.
    A heartbeat whose queue depth was nested that deep was kept, and every status failed to pack from then on
    (and with it executors' withdrawals and `apply --wait`)."""
    import zmq

    from shared import control

    address, _, _, t = plane
    nested = b"\x91" * 1000 + b"\x90"  # msgpack: [[[...[]...]]], 1000 deep
    assert request(address, "register", **REGISTER)["kind"] == "registered"
    ctx = zmq.Context.instance()
    for body in (b"\x81\xa4kind" + nested,
                 b"\x83\xa4kind\xa9heartbeat\xa8executor\xa3ex0\xa6depths\x81\xa5toy-a" + nested):
        sock = ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(address)
        try:
            sock.send(body)
            assert sock.poll(int(WAIT_S * 1000)), "no answer"
            reply = control.unpack(sock.recv())
        finally:
            sock.close()
        assert reply["kind"] == "error" and reply["code"] == "BAD_REQUEST", reply
    status = control_status(address, WAIT_S)
    assert status is not None and status["executors"]["ex0"]["depths"] == {}
    assert t.is_alive()
