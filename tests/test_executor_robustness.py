"""The executor under faults: a telemetry file that cannot be written, and SIGTERM under traffic.

Every request an executor accepts must be answered exactly once, and a replica leaving on
SIGTERM must not cost robots an error while a healthy replica serves the same model.
"""

import logging
import os
import signal
import threading
import time

import numpy as np
import pytest

from services.executor.engine import MonolithicEngine, ServedModel
from services.executor.telemetry import LockstepRecord, Telemetry
from shared.client import RobotClient, wait_any
from shared.cluster import LocalCluster, control_status
from shared.config import EngineConfig, load_config
from shared.models import build_model
from tests.helpers import cluster_config
from tests.test_lockstep import CPU, Collector, drive, engine_for, make_req

needs_dev_full = pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (a device that is always full)")


def _record(i: int) -> LockstepRecord:
    return LockstepRecord(index=i, start=0.0, vlm_model="toy", vlm_arch="toy", vlm_batch=1, action_model=None,
                          action_arch=None, action_batch=0, sm_level=None, duration_ms=1.0, vlm_ms=1.0, action_ms=0.0)


def _run_engine(eng, reqs, sink: Collector) -> list[BaseException]:
    """Run the engine thread as the executor does, submit ``reqs``, stop once ``sink`` holds their answers
    (or after 30 s); returns what escaped the thread. Stopping earlier would answer a request the loop has
    not taken yet UNAVAILABLE, which is the shutdown's job, not what these tests look at."""
    escaped: list[BaseException] = []
    expected = len(sink.results) + len(reqs)

    def target(stop):
        try:
            eng.run(stop)
        except BaseException as exc:  # what would kill the executor's engine thread
            escaped.append(exc)

    stop = threading.Event()
    t = threading.Thread(target=target, args=(stop,), daemon=True)
    t.start()
    for r in reqs:
        eng.submit(r)
        time.sleep(0.005)
    deadline = time.monotonic() + 30
    while len(sink.results) < expected and time.monotonic() < deadline and t.is_alive():
        time.sleep(0.005)
    stop.set()
    t.join(30)
    assert not t.is_alive(), "engine thread did not stop"
    return escaped


def _toy_requests(model, n: int) -> list:
    rng = np.random.default_rng(0)
    reqs = [make_req(model, f"r{i}", rng) for i in range(n)]
    for r in reqs:
        r.model = "toy"
    return reqs


@needs_dev_full
def test_telemetry_file_failure_is_logged_once_and_dropped(caplog):
    tel = Telemetry(path="/dev/full")
    with caplog.at_level(logging.WARNING, logger="services.executor.telemetry"):
        for i in range(5):
            tel.add(_record(i))
    assert tel.file_failed and len(tel.records()) == 5 and tel.count == 5  # the ring buffer carries on
    assert sum("telemetry file" in r.getMessage() for r in caplog.records) == 1
    tel.close()
    tel.close()


def test_telemetry_survives_a_closed_file_and_an_unopenable_path(tmp_path, caplog):
    tel = Telemetry(path=tmp_path / "t.jsonl")
    tel.add(_record(0))
    tel._file.close()  # closed under us: write raises ValueError
    tel.add(_record(1))
    tel.close()
    assert tel.file_failed and [r.index for r in tel.records()] == [0, 1]
    caplog.clear()
    blocker = tmp_path / "file"
    blocker.write_text("")
    with caplog.at_level(logging.WARNING, logger="services.executor.telemetry"):
        bad = Telemetry(path=blocker / "sub" / "t.jsonl")  # its parent is a file: cannot be created
    bad.add(_record(0))
    bad.close()
    assert bad.file_failed and len(bad.records()) == 1
    assert sum("telemetry file" in r.getMessage() for r in caplog.records) == 1


@needs_dev_full
@pytest.mark.parametrize("max_batch", [1, 2])
def test_lockstep_engine_with_full_telemetry_file_answers_every_request(max_batch):
    model = build_model("toy", seed=1)
    eng, sink = engine_for({"toy": (model, 60.0)}, max_batch=max_batch, telemetry_file="/dev/full")
    reqs = _toy_requests(model, 12)
    escaped = _run_engine(eng, reqs, sink)
    assert escaped == []
    assert sink.ids() == sorted(r.id for r in reqs)  # each exactly once
    assert all(res.error is None for res in sink.results)
    assert eng.telemetry.file_failed and eng.telemetry.count > 0


@needs_dev_full
def test_monolithic_engine_with_full_telemetry_file_answers_every_request():
    model = build_model("toy", seed=1)
    sink = Collector()
    eng = MonolithicEngine({"toy": ServedModel("toy", model, 60.0)},
                           EngineConfig(kind="monolithic", max_batch=2, telemetry_file="/dev/full"), CPU, sink)
    eng.prepare()
    reqs = _toy_requests(model, 12)
    assert _run_engine(eng, reqs, sink) == []
    assert sink.ids() == sorted(r.id for r in reqs)
    assert all(res.error is None for res in sink.results)


def test_lockstep_bookkeeping_failure_loses_no_request(monkeypatch):
    """Whatever fails after a lockstep's replies (timings, telemetry) must not lose the lockstep in flight."""
    model = build_model("toy", seed=1)
    eng, sink = engine_for({"toy": (model, 60.0)}, max_batch=2)

    def broken(*args):
        raise RuntimeError("bug")

    monkeypatch.setattr(eng.telemetry, "add", broken)
    monkeypatch.setattr(eng.stages["toy"], "prestage", broken)
    reqs = _toy_requests(model, 7)
    for r in reqs:
        eng.submit(r)
    drive(eng)
    assert sink.ids() == sorted(r.id for r in reqs)
    assert all(res.error is None for res in sink.results)


# ----------------------------------------------------------------------------- SIGTERM under traffic


def test_sigterm_withdraws_the_executor_before_it_stops(tmp_path):
    """SIGTERM one of two replicas mid-traffic: every request is answered, none with an error."""
    path, _ = cluster_config(tmp_path, executors=[{"name": "ex0", "device": "cpu", "models": ["toy-a"]},
                                                  {"name": "ex1", "device": "cpu", "models": ["toy-a"]}],
                             models=[{"name": "toy-a", "arch": "toy", "size": "tiny", "seed": 0, "slo_ms": 5000}])
    cfg = load_config(path)
    with LocalCluster(cfg, path, log_level="WARNING") as cluster:
        clients = [RobotClient(cfg.router.bind, robot_id=f"r{i}", timeout_s=30) for i in range(8)]
        try:
            info = clients[0].metadata()["toy-a"]
            images = {cam: np.zeros(info.image_shape, np.uint8) for cam in info.cameras}
            state = np.zeros(info.state_dim, np.float32)
            sent: set[str] = set()
            answers: dict[str, object] = {}
            duplicates = 0

            def collect(timeout_s: float) -> None:
                nonlocal duplicates
                for _, done in wait_any(clients, timeout_s):
                    duplicates += done.request_id in answers
                    answers[done.request_id] = done

            victim = cluster.procs["executor[ex0]"]
            t0 = time.monotonic()
            next_send = t0
            signalled = False
            while time.monotonic() - t0 < 2.5:  # each robot at 10 Hz; SIGTERM ex0 after 1 s
                now = time.monotonic()
                if now >= next_send:
                    sent |= {c.submit("toy-a", images, state) for c in clients}
                    next_send += 0.1
                if not signalled and now - t0 > 1.0:
                    victim.send_signal(signal.SIGTERM)
                    signalled = True
                collect(0.01)
            end = time.monotonic() + 30
            while len(answers) < len(sent) and time.monotonic() < end:
                collect(0.2)
            errors = {rid: (d.error.code.value, d.error.message) for rid, d in answers.items() if not d.ok}
            assert set(answers) == sent and duplicates == 0, f"{len(sent) - len(answers)} unanswered"
            assert errors == {}
            assert victim.wait(timeout=30) == 0
            routes = control_status(cfg.control.bind, timeout_s=5.0)["table"]["routes"]
            assert routes["toy-a"] == ["ex1"]
        finally:
            for c in clients:
                c.close()


# ----------------------------------------------------------------------------- an engine that has stopped


@pytest.mark.parametrize("kind", ["monolithic", "robion", "procdisagg", "interdisagg"])
def test_a_request_submitted_after_the_engine_stopped_is_refused_not_lost(kind):
    """Once an engine's loop has ended (``finish`` answered everything queued), nothing reads its
    queues again: a request put there would never be answered. That happens when the I/O thread
    has read ``EngineSlot.engine`` and a reload stops that engine before the submit lands, or when
    procdisagg's loop ends on a dead stage process while the executor keeps routing to it. Such a
    submit must raise UNAVAILABLE (the I/O thread then answers it) instead of queueing silently."""
    from services.executor.engine import make_engine
    from shared.protocol import ErrorCode, ProtocolError

    model = build_model("toy", seed=1)
    sink = Collector()
    extra = {"procdisagg": {"procdisagg_workers": "thread"},
             "interdisagg": {"vlm_devices": "cpu", "action_devices": "cpu"}}.get(kind, {})
    eng = make_engine({"toy": ServedModel("toy", model, 60.0)}, EngineConfig(kind=kind, max_batch=2, **extra), CPU,
                      sink)
    eng.prepare()
    try:
        first, late = _toy_requests(model, 2)
        late.id = "late"
        assert _run_engine(eng, [first], sink) == []  # served, then the loop ended
        with pytest.raises(ProtocolError) as refused:
            eng.submit(late)
        assert refused.value.code == ErrorCode.UNAVAILABLE
        assert sink.ids() == ["r0"]
        # An engine run again (the capacity harness reuses one per epoch) takes requests again.
        again = _toy_requests(model, 1)[0]
        again.id = "again"
        assert _run_engine(eng, [again], sink) == []
        assert sink.ids() == ["again", "r0"]
    finally:
        close = getattr(eng, "close", None)
        if close is not None:
            close()


@pytest.mark.parametrize("kind", ["monolithic", "robion", "disagg", "static", "disjoint"])
@pytest.mark.parametrize("shed_late", [False, True])
def test_a_stopped_engine_is_freed_with_its_models_once_dropped(kind, shed_late):
    """With shed_late the engine held a closure over itself (a reference cycle): a stopped engine, and the
    models a reload had removed (on a GPU their weights and graphs), lived on until a full garbage collection,
    through the reload that needed the memory. Collection is off here, so only reference counts free them."""
    import gc
    import weakref

    from services.executor.hosting import EngineSlot, ModelStore
    from shared.config import ModelConfig

    # The first model a process builds stays referenced from frames torch keeps of that first build (freed by a
    # collection): build one, collect, and measure from there.
    build_model("toy", "tiny", seed=2, device=CPU)
    gc.collect()
    gc.disable()
    try:
        store = ModelStore(CPU)
        slot = EngineSlot(EngineConfig(kind=kind, shed_late=shed_late), CPU, lambda results: None)
        slot.start(store.load([ModelConfig(name="toy-a", arch="toy", slo_ms=500)]))
        engine, model = weakref.ref(slot.engine), weakref.ref(slot.engine.models["toy-a"].model)
        slot.stop()
        store.load([ModelConfig(name="toy-b", arch="toy", seed=1, slo_ms=500)])  # a reload that drops toy-a
        assert engine() is None and model() is None
    finally:
        gc.enable()
