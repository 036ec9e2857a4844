"""The executor's I/O thread (services/executor/transport.py) on real sockets, in-process.

A real ``ExecutorIO`` with a real CPU engine serving the toy model is driven by a stand-in
router: a ZeroMQ ROUTER socket bound where the executor dials the router's backend, sending
requests exactly as the router forwards them (``[executor, robot envelope, *request]``).
"""

from __future__ import annotations

import threading
import time
from dataclasses import asdict

import numpy as np
import pytest
import torch
import zmq

from services.executor.hosting import EngineSlot, ModelStore
from services.executor.transport import ExecutorIO
from shared import control
from shared.config import load_config
from shared.metrics import ExecutorMetrics
from shared.protocol import ErrorCode, InferRequest, decode, encode
from tests.helpers import bound_router, cluster_config, free_ports, wait_for

CPU = torch.device("cpu")


class Harness:
    """An ExecutorIO serving in a thread, and a stand-in router holding the other end of its backend."""

    def __init__(self, tmp_path, models=("toy-a",), control_plane: bool = False, model_configs=None, **overrides):
        # ex1 (never started) hosts every model, so a model ex0 does not serve is still configured.
        if model_configs is not None:
            overrides["models"] = model_configs
        path, data = cluster_config(tmp_path, executors=[{"name": "ex0", "device": "cpu", "models": list(models)},
                                                         {"name": "ex1", "device": "cpu", "models": ["toy-a", "toy-b"]}],
                                    **overrides)
        self.cfg = load_config(path)
        self.ctx = zmq.Context()
        self.router = self.ctx.socket(zmq.ROUTER)
        self.router.setsockopt(zmq.LINGER, 0)
        self.router.bind(self.cfg.router.backend)
        self.control: zmq.Socket | None = None  # a stand-in control plane: reads what the executor sends
        if control_plane:
            self.control = self.ctx.socket(zmq.ROUTER)
            self.control.setsockopt(zmq.LINGER, 0)
            self.control.bind(self.cfg.control.bind)
        self.store = ModelStore(CPU)
        hosted = self.store.load([self.cfg.model(m) for m in models])
        self.slot = EngineSlot(self.cfg.engine, CPU, lambda results: self.io.on_results(results))
        self.metrics = ExecutorMetrics("ex0", "cpu", {n: s.slo_s for n, s in hosted.inputs.items()})
        self.io = ExecutorIO("ex0", self.cfg, "cpu", self.store, self.slot, hosted, self.metrics, context=self.ctx)
        self.slot.start(hosted)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.io.run, args=(self.stop,), name="io", daemon=True)
        self.thread.start()
        self._wait_hello()
        self.replies: dict[object, object] = {}
        self.closed = False

    def _wait_hello(self) -> None:
        assert self.router.poll(10_000), "the executor never said hello"
        self.router.recv_multipart()

    def request(self, rid, model: str = "toy-a") -> InferRequest:
        io = self.io.served[model].io if model in self.io.served else next(iter(self.io.served.values())).io
        return InferRequest(id=rid, robot="r0", model=model,
                            images={c: np.zeros(io.image_shape, np.uint8) for c in io.cameras},
                            state=np.zeros(io.state_dim, np.float32), instruction="pick")

    def send(self, msg: InferRequest) -> None:
        self.router.send_multipart([b"ex0", b"robot-0", *encode(msg)], copy=True)

    def collect(self, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while self.router.poll(max(1, int((end - time.monotonic()) * 1000))):
            frames = self.router.recv_multipart()
            if frames[1] == b"":  # the executor's hello (it says it again when it re-registers)
                continue
            assert frames[0] == b"ex0" and frames[1] == b"robot-0"
            msg = decode(frames[2:])
            assert msg.id not in self.replies, f"{msg.id!r} answered twice"
            self.replies[msg.id] = msg
            if time.monotonic() >= end:
                break

    def wait_replies(self, ids, timeout_s: float = 30.0) -> None:
        end = time.monotonic() + timeout_s
        while not set(ids) <= set(self.replies) and time.monotonic() < end:
            self.collect(0.05)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.stop.set()
        self.thread.join(10)
        if self.thread.is_alive():
            return  # wedged: leave its sockets (closing them under a blocked send is not safe)
        self.slot.stop()
        self.io.drain(1.0)
        self.io.close()
        self.router.close()
        if self.control is not None:
            self.control.close()
        self.ctx.term()

    def control_messages(self, timeout_s: float) -> list[dict]:
        """What the executor sent the stand-in control plane within ``timeout_s``."""
        out = []
        end = time.monotonic() + timeout_s
        while self.control.poll(max(1, int((end - time.monotonic()) * 1000))):
            out.append(control.unpack(self.control.recv_multipart()[1]))
            if time.monotonic() >= end:
                break
        return out

    def reload(self, models: list[str], timeout_s: float = 30.0) -> None:
        """Send the control plane's ``load``, wait for the executor to register its new model set,
        then for one heartbeat after it."""
        self.control.send_multipart([b"ex0", control.pack("load", models=[asdict(self.cfg.model(m)) for m in models])])
        end = time.monotonic() + timeout_s
        registered = False
        while time.monotonic() < end:
            for msg in self.control_messages(0.05):
                if msg.get("kind") == "register" and sorted(msg["models"]) == sorted(models):
                    registered = True
                elif registered and msg.get("kind") == "heartbeat":
                    return
        raise AssertionError(f"the executor did not reload to {models}")


@pytest.fixture
def harness(tmp_path):
    made: list[Harness] = []

    def make(**kw) -> Harness:
        h = Harness(tmp_path, **kw)
        made.append(h)
        return h

    yield make
    for h in made:
        h.close()


def test_executor_keeps_serving_and_leaves_while_the_control_plane_is_unreachable(harness):
    """Nothing listens at the control plane's address (it crashed, or is restarting): heartbeats
    cannot be delivered, but robots must still be answered and SIGTERM must still end the
    process. ZeroMQ queues 1000 undeliverable messages, then a blocking send waits forever."""
    (dead,) = free_ports(1)
    h = harness(control={"bind": f"tcp://127.0.0.1:{dead}", "heartbeat_s": 0.01, "missed_heartbeats": 5,
                         "metrics_port": 0})
    # Below the config's floor (0.01 s), set on the loaded config the I/O loop reads: a heartbeat on every turn of
    # the loop, so well past ZeroMQ's 1000 queued messages within the test.
    h.io.cfg.control.heartbeat_s = 1e-6
    ids = []
    for i in range(1500):  # every turn of the I/O loop sends a heartbeat: well past 1000 of them
        ids.append(i)
        h.send(h.request(i))
        h.collect(0.002)
    h.wait_replies(ids, timeout_s=20)
    missing = [i for i in ids if i not in h.replies]
    assert not missing, f"{len(missing)} of {len(ids)} requests never answered (first: {missing[:3]})"

    # Shutdown as main() runs it: withdraw (its waits are bounded), then close (deregisters).
    h.stop.set()
    h.thread.join(10)
    assert not h.thread.is_alive(), "the I/O thread is wedged"
    done = threading.Event()

    def leave():
        h.io.withdraw(ack_timeout_s=0.5, answer_timeout_s=0.5)
        h.io.close()
        done.set()

    t0 = time.monotonic()
    threading.Thread(target=leave, daemon=True).start()
    assert done.wait(15), "withdraw/close blocked on the unreachable control plane"
    assert time.monotonic() - t0 < 5
    h.closed = True  # already left: the fixture must not close it twice
    h.slot.stop()
    h.router.close()
    h.ctx.term()


def _sample(h: Harness, name: str, **labels) -> float:
    return h.metrics.registry.get_sample_value(name, labels) or 0.0


def test_requests_refused_at_the_executor_count_in_requests_and_slo_metrics(harness):
    """A request refused when it arrives (queue full, wrong shape) is answered with an error:
    robion_requests_total counts it under its code, and the SLO series count it as missed,
    as they do errors the engine answers (DEADLINE_EXCEEDED, UNAVAILABLE). Otherwise an
    executor refusing most requests as OVERLOADED reports an attainment of 1.0."""
    h = harness(engine={"kind": "monolithic", "max_batch": 1, "max_queue": 1})
    ids = list(range(40))
    for i in ids:  # one burst: the I/O thread submits faster than the engine drains a queue of one
        h.send(h.request(i))
    bad = h.request("bad")
    bad.state = np.zeros(3, np.float32)
    h.send(bad)
    h.wait_replies([*ids, "bad"])
    codes = {rid: getattr(m, "code", None) for rid, m in h.replies.items()}
    overloaded = sum(c == ErrorCode.OVERLOADED for c in codes.values())
    ok = sum(c is None for c in codes.values())
    assert overloaded > 0 and ok > 0 and codes["bad"] == ErrorCode.SHAPE_MISMATCH
    assert _sample(h, "robion_requests_total", model="toy-a", status="overloaded") == overloaded
    assert _sample(h, "robion_requests_total", model="toy-a", status="shape_mismatch") == 1
    assert _sample(h, "robion_requests_total", model="toy-a", status="ok") == ok
    met = _sample(h, "robion_slo_met_total", model="toy-a")
    missed = _sample(h, "robion_slo_missed_total", model="toy-a")
    assert met + missed == len(h.replies)  # every answer is one SLO event
    assert missed >= overloaded + 1
    assert _sample(h, "robion_slo_attainment_ratio", model="toy-a") == pytest.approx(met / len(h.replies))


def test_a_reload_drops_the_gauges_of_models_no_longer_served(harness):
    """After a placement change moves toy-b away, robion_queue_depth and
    robion_slo_attainment_ratio no longer show a toy-b series for this executor (they would
    otherwise keep their last values forever), and the models served have their depth."""
    h = harness(models=("toy-a", "toy-b"), control_plane=True,
                control={"bind": f"tcp://127.0.0.1:{free_ports(1)[0]}", "heartbeat_s": 0.05, "metrics_port": 0})
    ids = [f"b{i}" for i in range(4)]
    for rid in ids:
        h.send(h.request(rid, "toy-b"))
    h.wait_replies(ids)
    assert _sample(h, "robion_queue_depth", model="toy-b") == 0
    h.reload(["toy-a"])
    reg = h.metrics.registry
    assert reg.get_sample_value("robion_queue_depth", {"model": "toy-b"}) is None
    assert reg.get_sample_value("robion_slo_attainment_ratio", {"model": "toy-b"}) is None
    assert reg.get_sample_value("robion_queue_depth", {"model": "toy-a"}) == 0
    h.reload(["toy-a", "toy-b"])  # and back: its series return
    assert reg.get_sample_value("robion_queue_depth", {"model": "toy-b"}) == 0


def test_a_request_for_a_model_moved_away_is_answered_unavailable(harness):
    """The router forwards only models of its routing table; one that reaches an executor
    that does not serve it (now) was routed by a table older than the executor's model set
    (a placement change in progress, a replica restarted with other models). The model is
    configured, so the answer is UNAVAILABLE (retry: another host serves it), never
    UNKNOWN_MODEL, which docs/protocol.md keeps for names the cluster does not define."""
    h = harness(models=("toy-a", "toy-b"), control_plane=True,
                control={"bind": f"tcp://127.0.0.1:{free_ports(1)[0]}", "heartbeat_s": 0.05, "metrics_port": 0})
    h.reload(["toy-a"])
    h.send(h.request("late", "toy-b"))
    h.send(h.request("fine", "toy-a"))
    # A model an `apply` added, routed here by a table from before this executor restarted with its own config
    # file, which does not name it: UNKNOWN_MODEL told the robot never to retry a model the cluster serves.
    h.send(h.request("applied", "toy-applied"))
    h.wait_replies(["late", "fine", "applied"])
    assert h.replies["late"].code == ErrorCode.UNAVAILABLE
    assert h.replies["applied"].code == ErrorCode.UNAVAILABLE
    assert getattr(h.replies["fine"], "actions", None) is not None


def test_a_result_that_cannot_be_encoded_is_answered_internal_and_the_loop_goes_on(harness):
    """An engine fault that hands the I/O thread a result with neither actions nor an error
    costs that one request an INTERNAL answer (before, the robot got an ok reply without
    actions), and a result whose reply cannot be encoded does too, without ending the I/O loop."""
    from services.executor.scheduler import Request, Result

    h = harness()
    io = h.io.served["toy-a"].io
    now = time.monotonic()
    broken = Request(id="broken", robot="r0", model="toy-a",
                     images=np.zeros((len(io.cameras), *io.image_shape), np.uint8),
                     state=np.zeros(io.state_dim, np.float32), tokens=np.zeros(io.prompt_len, np.int64),
                     arrival=now, deadline=now + 1.0, envelope=b"robot-0")
    unencodable = Request(**{**broken.__dict__, "id": "unencodable"})
    # A finite but extreme state can overflow inside a model: its NaN actions were sent as an ok reply.
    nan = Request(**{**broken.__dict__, "id": "nan"})
    actions = np.zeros((io.horizon, io.action_dim), np.float32)
    actions[0, 0] = np.nan
    h.io.on_results([Result(broken), Result(unencodable, actions=object()), Result(nan, actions=actions)])
    h.wait_replies(["broken", "unencodable", "nan"], timeout_s=10)
    assert h.replies["broken"].code == ErrorCode.INTERNAL
    assert h.replies["unencodable"].code == ErrorCode.INTERNAL
    assert h.replies["nan"].code == ErrorCode.INTERNAL and "non-finite" in h.replies["nan"].message
    assert _sample(h, "robion_requests_total", model="toy-a", status="internal") == 3  # counted as what was sent
    h.send(h.request("after"))
    h.wait_replies(["after"], timeout_s=30)
    assert getattr(h.replies["after"], "actions", None) is not None
    assert h.thread.is_alive()


def test_a_shutdown_waits_for_a_drain_answered_after_the_traffic_solve(harness, caplog):
    """The control plane re-solves the traffic plan before it answers an executor's drain (up to
    control.solve_time_limit_s, 5 s by default). A leaving executor waited 1 s for that answer, then left
    without waiting for the router to switch tables: requests routed to it meanwhile were answered
    UNAVAILABLE. Here the stand-in plane answers after 3.5 s, within a 4 s solve limit: longer than the 3 s the
    executor waits for the router, which once counted from the drain, not from its answer (no wait was left)."""
    import logging

    h = harness(control_plane=True, control={"bind": f"tcp://127.0.0.1:{free_ports(1)[0]}", "heartbeat_s": 0.2,
                                             "solve_time_limit_s": 4, "metrics_port": 0})
    h.stop.set()
    h.thread.join(10)
    done = threading.Event()

    def leave() -> None:
        h.io.withdraw(ack_timeout_s=3.0, answer_timeout_s=0.2)
        done.set()

    with caplog.at_level(logging.INFO, logger="robion.executor"):
        threading.Thread(target=leave, daemon=True).start()
        drained = None
        end = time.monotonic() + 10
        while drained is None and time.monotonic() < end:  # registration and heartbeats come first
            assert h.control.poll(10_000)
            peer, frame = h.control.recv_multipart()
            if control.unpack(frame).get("kind") == "drain":
                drained = peer
        assert drained is not None, "the executor never sent its drain"
        time.sleep(3.5)  # the solve
        h.control.send_multipart([drained, control.pack("ok", version=7)])
        while not done.is_set() and h.control.poll(3000):  # status polls: the router is on v7
            peer, frame = h.control.recv_multipart()
            if control.unpack(frame).get("kind") == "status":
                h.control.send_multipart([peer, control.pack("status", status={"router": {"version": 7}})])
        assert done.wait(10)
    assert "withdrawn from routing (table v7)" in caplog.text, caplog.text
    assert "did not answer our drain" not in caplog.text


def test_an_executor_whose_engine_fails_every_batch_leaves(harness):
    """A sticky device fault (on a GPU, an illegal memory access fails every later launch) made every batch fail:
    the executor answered its whole share of the fleet INTERNAL while it heartbeated as healthy, so routing kept
    sending it traffic. After FAILED_IN_ROW_FATAL failed requests in a row it now ends its I/O loop (main then
    withdraws and exits 1 for a supervisor to restart it). One failed batch among good ones does not."""
    from services.executor.transport import ExecutorIO

    h = harness(engine={"kind": "robion", "max_batch": 2})
    stage = h.io.slot.engine.stages["toy-a"]
    healthy = stage.model.action_stage

    def faulted(*args, **kwargs):
        raise RuntimeError("CUDA error: an illegal memory access was encountered")

    stage.model.action_stage = faulted
    h.send(h.request("once"))
    h.wait_replies(["once"], timeout_s=30)
    stage.model.action_stage = healthy
    h.send(h.request("after"))
    h.wait_replies(["after"], timeout_s=30)
    assert h.replies["once"].code == ErrorCode.INTERNAL and getattr(h.replies["after"], "actions", None) is not None
    assert h.thread.is_alive() and not h.io.fatal.is_set()

    stage.model.action_stage = faulted  # now for good
    ids = [f"q{i}" for i in range(ExecutorIO.FAILED_IN_ROW_FATAL)]
    for rid in ids:
        h.send(h.request(rid))
        time.sleep(0.01)
    h.wait_replies(ids, timeout_s=60)
    assert {h.replies[rid].code for rid in ids} == {ErrorCode.INTERNAL}  # every request still answered
    h.thread.join(10)
    assert not h.thread.is_alive() and h.io.fatal.is_set()
    assert "in a row" in h.io.fatal_reason


def test_an_executor_that_cannot_load_any_models_after_a_failed_reload_leaves(harness, tmp_path):
    """A load whose models fail, while the previous models cannot be loaded back either (here
    their weights file is gone), leaves no engine: the executor ends its I/O loop (main then
    withdraws and exits 1 for a supervisor to restart it) instead of staying registered and
    answering every request UNAVAILABLE forever."""
    from shared.models import build_model
    from shared.models.weights import save_weights

    weights = tmp_path / "toy-a.safetensors"
    save_weights(build_model("toy", "tiny", seed=0), str(weights))
    models = [{"name": "toy-a", "arch": "toy", "size": "tiny", "seed": 0, "slo_ms": 500, "weights": str(weights)},
              {"name": "toy-b", "arch": "toy", "size": "tiny", "seed": 1, "slo_ms": 500}]
    h = harness(model_configs=models, control_plane=True,
                control={"bind": f"tcp://127.0.0.1:{free_ports(1)[0]}", "heartbeat_s": 0.05, "metrics_port": 0})
    h.send(h.request("before"))
    h.wait_replies(["before"])
    assert getattr(h.replies["before"], "actions", None) is not None
    weights.unlink()  # e.g. the weights volume went away
    broken = {**asdict(h.cfg.model("toy-b")), "weights": str(tmp_path / "missing.safetensors")}
    h.control.send_multipart([b"ex0", control.pack("load", models=[broken])])
    h.thread.join(30)
    assert not h.thread.is_alive() and h.io.fatal.is_set()


def _load_and_wait_registration(h: Harness, models: list[str], timeout_s: float = 30.0) -> dict:
    """Send the control plane's ``load``; the executor's first registration after it (its outcome in ``load``)."""
    h.control.send_multipart([b"ex0", control.pack("load", models=[asdict(h.cfg.model(m)) for m in models],
                                                   load_id="L1")])
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        for msg in h.control_messages(0.05):
            if msg.get("kind") == "register" and (msg.get("load") or {}).get("id") == "L1":
                return msg
    raise AssertionError(f"the executor did not register after the load of {models}")


def test_a_failed_reload_frees_the_failed_engine_and_models_before_falling_back(harness, monkeypatch):
    """A reload that fails (most often: the device ran out of memory building the new models or capturing their
    graphs) falls back to the previous models. The fallback ran inside the except block, whose traceback held the
    failed engine and the new models' weights, so on a full device the fallback could run out of memory too, and the
    executor left instead of going back to its previous models as docs/operations.md says."""
    import gc
    import weakref

    from services.executor.engine import MonolithicEngine

    h = harness(control_plane=True,
                control={"bind": f"tcp://127.0.0.1:{free_ports(1)[0]}", "heartbeat_s": 0.05, "metrics_port": 0})
    real = MonolithicEngine.prepare
    seen: dict = {}

    def prepare(self):
        if "toy-b" in self.models:  # the new set's engine fails after allocating
            self.buffers = torch.zeros(1 << 20)
            seen["engine"], seen["model"] = weakref.ref(self), weakref.ref(self.models["toy-b"].model)
            raise RuntimeError("CUDA out of memory (simulated)")
        if seen:  # the fallback's engine: is the failed attempt's memory free by now?
            gc.collect()
            seen["alive during fallback"] = (seen["engine"]() is not None, seen["model"]() is not None)
        real(self)

    monkeypatch.setattr(MonolithicEngine, "prepare", prepare)
    msg = _load_and_wait_registration(h, ["toy-a", "toy-b"])
    assert msg["load"]["ok"] is False and "CUDA out of memory (simulated)" in msg["load"]["error"]
    assert sorted(msg["models"]) == ["toy-a"]
    assert seen["alive during fallback"] == (False, False)
    h.send(h.request("after"))
    h.wait_replies(["after"])
    assert getattr(h.replies["after"], "actions", None) is not None


def test_a_failed_reload_keeps_the_attainment_window_of_the_models_it_keeps(harness, monkeypatch):
    """A failed reload empties the served set while it loads the previous models back. A heartbeat then dropped every
    model's series, and toy-a came back with a fresh window reading 1.0, its model and deadline unchanged and every
    reply so far a miss (a deadline of a microsecond)."""
    from services.executor.engine import MonolithicEngine

    models = [{"name": "toy-a", "arch": "toy", "size": "tiny", "seed": 0, "slo_ms": 0.001},
              {"name": "toy-b", "arch": "toy", "size": "tiny", "seed": 1, "slo_ms": 500}]
    h = harness(model_configs=models, engine={"kind": "monolithic", "max_batch": 2, "shed_expired": False},
                control_plane=True,
                control={"bind": f"tcp://127.0.0.1:{free_ports(1)[0]}", "heartbeat_s": 0.05, "metrics_port": 0})
    ids = [f"a{i}" for i in range(4)]
    for rid in ids:
        h.send(h.request(rid))
    h.wait_replies(ids)

    def ratio():
        return h.metrics.registry.get_sample_value("robion_slo_attainment_ratio", {"model": "toy-a"})

    assert wait_for(lambda: ratio() == 0.0, 5)
    real_prepare, real_load = MonolithicEngine.prepare, ModelStore.load

    def prepare(self):
        if "toy-b" in self.models:
            raise RuntimeError("CUDA out of memory (simulated)")
        real_prepare(self)

    def load(self, configs):  # loading takes a while (seconds on a GPU): several heartbeats pass
        time.sleep(0.3)
        return real_load(self, configs)

    monkeypatch.setattr(MonolithicEngine, "prepare", prepare)
    monkeypatch.setattr(ModelStore, "load", load)
    msg = _load_and_wait_registration(h, ["toy-a", "toy-b"])
    assert msg["load"]["ok"] is False and sorted(msg["models"]) == ["toy-a"]
    time.sleep(0.2)
    assert ratio() == 0.0
    assert _sample(h, "robion_slo_missed_total", model="toy-a") == 4


def test_replies_right_after_a_reload_are_judged_by_the_new_deadlines(harness):
    """The metrics learnt a reload's model set at the next heartbeat, but the registration before it lets traffic in:
    replies in between were judged by the old deadline, or by none (a model just added: every reply counted met).
    toy-b's deadline here is a microsecond, so each of its replies is a miss."""
    models = [{"name": "toy-a", "arch": "toy", "size": "tiny", "seed": 0, "slo_ms": 500},
              {"name": "toy-b", "arch": "toy", "size": "tiny", "seed": 1, "slo_ms": 0.001}]
    h = harness(model_configs=models, engine={"kind": "monolithic", "max_batch": 2, "shed_expired": False},
                control_plane=True,
                control={"bind": f"tcp://127.0.0.1:{free_ports(1)[0]}", "heartbeat_s": 30, "metrics_port": 0})
    _load_and_wait_registration(h, ["toy-a", "toy-b"])
    ids = [f"b{i}" for i in range(4)]
    for rid in ids:
        h.send(h.request(rid, "toy-b"))
    h.wait_replies(ids)
    assert all(getattr(h.replies[rid], "actions", None) is not None for rid in ids)
    assert _sample(h, "robion_slo_met_total", model="toy-b") == 0
    assert _sample(h, "robion_slo_missed_total", model="toy-b") == 4
    assert h.metrics.registry.get_sample_value("robion_slo_attainment_ratio", {"model": "toy-b"}) == 0.0


@pytest.mark.parametrize("engine", [{"kind": "procdisagg", "procdisagg_workers": "thread"},
                                    {"kind": "interdisagg", "vlm_devices": "cpu", "action_devices": "cpu"}],
                         ids=["procdisagg", "interdisagg"])
def test_heartbeats_survive_the_telemetry_of_every_engine_kind(harness, engine):
    """Each heartbeat feeds the engine's telemetry records into the metrics. The comparison engines
    keep records of their own kind (per denoising step, per batch) without a lockstep duration:
    the I/O loop must not die on them (before, the first heartbeat after a reply raised
    AttributeError and ended the executor's I/O thread, so nothing more was answered)."""
    h = harness(engine={"max_batch": 1, **engine},
                control={"bind": f"tcp://127.0.0.1:{free_ports(1)[0]}", "heartbeat_s": 0.05, "metrics_port": 0})
    h.send(h.request("first"))
    h.wait_replies(["first"])
    assert getattr(h.replies["first"], "actions", None) is not None
    time.sleep(0.3)  # several heartbeats, with the first reply's telemetry record in the ring
    assert h.thread.is_alive()
    h.send(h.request("second"))
    h.wait_replies(["second"], timeout_s=10)
    assert getattr(h.replies.get("second"), "actions", None) is not None


def test_replies_the_router_cannot_take_do_not_wedge_the_executor(harness):
    """Replies went out with a blocking send. With the router gone and over ~1000 answers waiting (ZeroMQ's
    high-water mark for the lost peer), the I/O thread blocked in that send for good: no heartbeats, no control
    messages, and a stop was never seen. Now they wait in order and go out when a router takes them again."""
    models = [{"name": n, "arch": "toy", "size": "tiny", "seed": 0, "slo_ms": 600_000} for n in ("toy-a", "toy-b")]
    h = harness(control_plane=True, model_configs=models, engine={"kind": "monolithic", "max_batch": 1, "max_queue": 2000})
    gate = threading.Event()
    engine = h.slot.engine
    step = engine.step
    engine.step = lambda: (gate.wait(), step())[1]
    n = 1200
    for i in range(n):
        h.send(h.request(i))
    end = time.monotonic() + 30
    while h.io.in_flight < n and time.monotonic() < end:
        time.sleep(0.05)
    assert h.io.in_flight == n
    address = h.cfg.router.backend
    h.router.close(linger=0)  # the router process dies
    gate.set()
    end = time.monotonic() + 30
    while h.io.in_flight and time.monotonic() < end:
        time.sleep(0.05)
    assert h.io.in_flight == 0 and h.io._unsent, (h.io.in_flight, len(h.io._unsent))  # held, not blocked on
    h.control_messages(0.1)
    assert any(m.get("kind") == "heartbeat" for m in h.control_messages(1.0)), "the I/O loop stopped"
    # A router on the same address (restarted) gets the held replies, each once, in order.
    h.router = h.ctx.socket(zmq.ROUTER)
    h.router.setsockopt(zmq.LINGER, 0)
    h.router.bind(address)
    h.collect(10.0)
    ids = list(h.replies)  # in the order they arrived (collect() refuses a second answer to an id)
    assert len(ids) >= n - 1000 and ids == list(range(n - len(ids), n)), (len(ids), ids[:3], ids[-3:])
    h.close()
    assert not h.thread.is_alive()


def test_requests_routed_here_while_the_engine_starts_are_answered_unavailable_at_once(tmp_path):
    """A real executor process whose engine takes 3 s to start (graph capture takes minutes on a GPU). The router
    routes to its name by the entry of an earlier process until that entry times out: those requests sat in the
    socket for the whole start and were then served as if they had just come, actions for observations seconds
    old counted as within their deadline. They are refused at once now, and the started executor serves."""
    import os
    import signal
    import subprocess
    import sys

    path, _ = cluster_config(tmp_path)
    cfg = load_config(path)
    ctx = zmq.Context()
    router = bound_router(ctx, cfg.router.backend)
    slow_start = ("import time\nfrom services.executor import hosting\nstart = hosting.EngineSlot.start\n"
                  "def slow(self, hosted):\n    time.sleep(3.0)\n    return start(self, hosted)\n"
                  "hosting.EngineSlot.start = slow\nfrom services.executor.main import main\nraise SystemExit(main())\n")
    proc = subprocess.Popen([sys.executable, "-c", slow_start, "--config", str(path), "--name", "ex0"],
                            cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    rng = np.random.default_rng(0)
    io = ModelStore(CPU).load([cfg.model("toy-a")]).inputs["toy-a"].io  # the toy's input shapes

    def ask(rid: str, timeout_s: float):
        msg = InferRequest(id=rid, robot="r0", model="toy-a", instruction="pick",
                           images={c: rng.integers(0, 256, io.image_shape, dtype=np.uint8) for c in io.cameras},
                           state=np.zeros(io.state_dim, np.float32))
        t0 = time.monotonic()
        router.send_multipart([b"ex0", b"robot-0", *encode(msg)])
        while router.poll(int(timeout_s * 1000)):
            frames = router.recv_multipart()
            if frames[1] == b"":  # a hello
                continue
            return decode(frames[2:]), time.monotonic() - t0
        return None, time.monotonic() - t0

    try:
        assert router.poll(30_000), "the executor never said hello"
        assert router.recv_multipart()[0] == b"ex0"
        reply, took = ask("early", 2.0)
        assert reply is not None and reply.id == "early", "not answered during the engine's start"
        assert getattr(reply, "code", None) == ErrorCode.UNAVAILABLE and took < 1.0, (reply, took)
        end = time.monotonic() + 30
        while time.monotonic() < end:  # once the engine is up, the same request is served
            reply, _ = ask(f"late-{end}", 2.0)
            if reply is not None and getattr(reply, "code", None) is None:
                break
            time.sleep(0.2)
        assert reply is not None and reply.actions.shape[0] > 0, reply
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
        router.close()
        ctx.term()


def test_one_failed_lockstep_of_large_batches_does_not_end_the_executor(harness):
    """At max_batch 16 one transient fault in the action stage fails the lockstep's two batches at once: 32
    requests, which alone reached FAILED_IN_ROW_FATAL and made a healthy executor exit (warm graphs and SM table
    lost). A sticky fault still fails batch after batch, which the test above covers."""
    h = harness(engine={"kind": "robion", "max_batch": 16, "max_queue": 256})
    model = h.io.slot.engine.stages["toy-a"].model
    vlm, action = model.vlm_stage, model.action_stage
    queued = threading.Event()

    def vlm_after_the_burst(*args, **kwargs):
        queued.wait(30)  # the first batch holds the engine until every request is queued: then batches are full
        return vlm(*args, **kwargs)

    faults = iter([True])

    def action_failing_a_full_batch_once(handoff, noise, *args, **kwargs):
        if noise.shape[0] == 16 and next(faults, False):
            raise RuntimeError("CUDA error: unspecified launch failure")
        return action(handoff, noise, *args, **kwargs)

    model.vlm_stage, model.action_stage = vlm_after_the_burst, action_failing_a_full_batch_once
    ids = [f"b{i}" for i in range(96)]
    for rid in ids:
        h.send(h.request(rid))
    assert wait_for(lambda: h.io.slot.depths().get("toy-a", 0) >= 80, 30), h.io.slot.depths()
    queued.set()
    h.wait_replies(ids, timeout_s=60)
    failed = [rid for rid in ids if getattr(h.replies[rid], "code", None) == ErrorCode.INTERNAL]
    assert len(failed) == 32, f"{len(failed)} failed: the fault did not fail two full batches at once"
    h.send(h.request("after"))
    h.wait_replies(["after"], timeout_s=30)
    assert getattr(h.replies["after"], "actions", None) is not None
    assert h.thread.is_alive() and not h.io.fatal.is_set()


def test_a_shutdown_does_not_wait_out_the_solve_limit_of_a_control_plane_that_is_down(harness):
    """Nothing listens at the control plane's address. A drain to it is queued, not refused, so withdraw() waited
    out the plane's solve limit plus a second for an answer that could not come: 31 s here, past a container's
    30 s stop grace (docker then kills the executor before its engine answers what it holds)."""
    (dead,) = free_ports(1)
    h = harness(control={"bind": f"tcp://127.0.0.1:{dead}", "solve_time_limit_s": 30, "metrics_port": 0})
    h.send(h.request("r"))
    h.wait_replies(["r"], timeout_s=30)
    h.stop.set()
    h.thread.join(10)
    t0 = time.monotonic()
    h.io.withdraw(ack_timeout_s=0.5, answer_timeout_s=0.5)
    assert time.monotonic() - t0 < 5


def test_an_executor_whose_engine_loop_ends_on_a_fault_leaves(harness):
    """procdisagg's loop ends when a stage dies. The executor stayed registered and heartbeating, refusing its whole
    share of the fleet UNAVAILABLE (which no failure count sees); it now leaves for a restart at its next heartbeat."""
    h = harness(engine={"kind": "procdisagg", "procdisagg_workers": "thread", "max_batch": 2},
                control={"bind": f"tcp://127.0.0.1:{free_ports(1)[0]}", "heartbeat_s": 0.05, "metrics_port": 0})
    h.send(h.request("before"))
    h.wait_replies(["before"])
    assert getattr(h.replies["before"], "actions", None) is not None
    h.slot.engine._handle(("fatal", "action process: stand-in for a stage that died"))
    h.thread.join(10)
    assert not h.thread.is_alive() and h.io.fatal.is_set(), "the executor stayed up with no engine loop"
    assert "engine's loop ended" in h.io.fatal_reason


def test_heartbeats_are_not_queued_for_a_control_plane_that_is_down(harness):
    """While nothing listens at the control plane's address, heartbeats are skipped, not queued: a plane that comes
    back would otherwise read the whole backlog at once (one heartbeat per turn of the outage) and, not knowing this
    executor yet, ask it to re-register once for each of them."""
    (port,) = free_ports(1)
    address = f"tcp://127.0.0.1:{port}"
    h = harness(control={"bind": address, "heartbeat_s": 0.02, "metrics_port": 0})
    time.sleep(2.0)  # the outage
    plane = h.ctx.socket(zmq.ROUTER)  # the control plane comes back
    plane.setsockopt(zmq.LINGER, 0)
    plane.bind(address)

    def kinds_within(seconds: float) -> list[str]:
        kinds: list[str] = []
        end = time.monotonic() + seconds
        while plane.poll(max(1, int((end - time.monotonic()) * 1000))):
            kinds.append(control.unpack(plane.recv_multipart()[-1])["kind"])
            if time.monotonic() >= end:
                break
        return kinds

    try:
        first, steady = kinds_within(0.5), kinds_within(0.5)
        # The registration sent at start waits for the plane (it is sent once). Heartbeats resume on the new connection
        # at their steady rate: the first half second holds about as many as the next (a backlog held 4x more; the
        # margin of 10 is for a loaded host, whose loop may stall in either half second).
        assert first.count("register") == 1 and "register" not in steady, (first, steady)
        assert steady.count("heartbeat") >= 3, steady
        assert first.count("heartbeat") <= steady.count("heartbeat") + 10, (first, steady)
    finally:
        plane.close()


def test_a_load_that_comes_during_a_reload_runs_after_it(harness, monkeypatch):
    """The control plane sends another load while a reload still runs (the first's rollout step timed out, then a later
    apply moved the models again): it runs once the first is done, and the registrations carry both outcomes in turn.
    It used to be ignored, and the executor kept the first load's models for good."""
    h = harness(models=("toy-a",), control_plane=True,
                control={"bind": f"tcp://127.0.0.1:{free_ports(1)[0]}", "heartbeat_s": 0.05, "metrics_port": 0})
    slow_load = h.store.load

    def load(configs):
        time.sleep(1.0)  # a reload that takes a while (weights, graphs, profiling on a GPU)
        return slow_load(configs)

    monkeypatch.setattr(h.store, "load", load)
    for load_id, models in (("first", ["toy-b"]), ("second", ["toy-a", "toy-b"])):
        h.control.send_multipart([b"ex0", control.pack("load", models=[asdict(h.cfg.model(m)) for m in models],
                                                       load_id=load_id)])
    outcomes = []
    end = time.monotonic() + 30
    while time.monotonic() < end and len(outcomes) < 2:
        for msg in h.control_messages(0.05):
            if msg.get("kind") == "register" and (msg.get("load") or {}).get("id") not in (None, *outcomes):
                outcomes.append(msg["load"]["id"])
                assert msg["load"]["ok"] is True, msg
                last = sorted(msg["models"])
    assert outcomes == ["first", "second"], outcomes
    assert last == ["toy-a", "toy-b"] and sorted(h.io.served) == ["toy-a", "toy-b"]
