"""Simulated robots and the capacity search (CPU, toy model, a few seconds per test)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from services.executor.engine import Engine, ServedModel
from services.executor.scheduler import Result
from services.executor.simulation import (CapacitySearch, EngineHost, Point, RobotGroup, SimConfig, SweepSearch,
                                          compare_capacity, engine_factory, find_capacity, make_schedule,
                                          measure_point, simulate, sweep)
from shared.config import EngineConfig
from shared.models import build_model
from shared.protocol import ErrorCode

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def toy():
    return build_model("toy", "tiny")


def served(toy, slo_ms: float) -> dict[str, ServedModel]:
    return {"toy": ServedModel("toy", toy, slo_ms / 1e3)}


class QueueModelEngine(Engine):
    """One server with a fixed service time per batch, kept in virtual time.

    A batch starts when the server is free and its last request has arrived, and is done
    ``service_s`` later; the reply is sent at once with that ``done``. Latencies then follow
    from the schedule alone (no thread timing), so the capacity is known analytically.
    """

    def __init__(self, models, cfg, device, on_results, service_s: float):
        super().__init__(models, cfg, device, on_results)
        self.service_s = service_s
        self.free = 0.0

    def step(self) -> bool:
        _, batch, _ = self.queues.take(self.cfg.max_batch)
        if not batch:
            return False
        start = max(self.free, max(r.arrival for r in batch))
        self.free = start + self.service_s
        io = self.models[batch[0].model].model.io
        self.on_results([Result(r, actions=np.zeros((io.horizon, io.action_dim), np.float32), done=self.free)
                         for r in batch])
        return True

    def finish(self) -> None:
        # Stopping answers everything: no virtual backlog may carry into the next epoch.
        super().finish()
        self.free = 0.0


class BlackHoleEngine(Engine):
    """Takes requests and never answers them."""

    def step(self) -> bool:
        _, batch, _ = self.queues.take(self.cfg.max_batch)
        return bool(batch)


def queue_model_factory(toy, slo_ms: float, service_s: float, max_batch: int = 1):
    cfg = EngineConfig(max_batch=max_batch, shed_expired=False)
    return lambda sink: QueueModelEngine(served(toy, slo_ms), cfg, CPU, sink, service_s)


# ----------------------------------------------------------------------------- schedule

def test_schedule_is_seeded_periodic_and_redrawn_per_epoch():
    work = [RobotGroup("a", 3, 2.0), RobotGroup("b", 2, 5.0)]
    one = make_schedule(work, 4.0, np.random.default_rng(np.random.SeedSequence([7, 0])))
    again = make_schedule(work, 4.0, np.random.default_rng(np.random.SeedSequence([7, 0])))
    other = make_schedule(work, 4.0, np.random.default_rng(np.random.SeedSequence([7, 1])))
    assert one == again
    assert [s.t for s in one] != [s.t for s in other]
    assert [s.t for s in one] == sorted(s.t for s in one)
    for g, group in enumerate(work):
        period = 1 / group.hz
        for r in range(group.robots):
            ts = [s.t for s in one if s.group == g and s.robot == r]
            assert 0 <= ts[0] < period
            assert np.allclose(np.diff(ts), period)  # on the robot's own clock
            assert ts[-1] < 4.0 <= ts[-1] + period + 1e-12
    assert len(one) == 3 * 8 + 2 * 20


def test_seeded_simulations_send_the_same_requests(toy):
    cfg = SimConfig(epochs=2, duration_s=0.3, drain_s=0.2, seed=3, network="none")
    work = [RobotGroup("toy", 8, 10)]
    a = simulate(queue_model_factory(toy, 100, 0.01), work, cfg)
    b = simulate(queue_model_factory(toy, 100, 0.01), work, cfg)
    # Virtual-time latencies (queueing at 80% load) depend on the schedule only: same seed, same numbers.
    assert [e.overall.sent for e in a.epochs] == [e.overall.sent for e in b.epochs] == [24, 24]
    assert a.models["toy"].epoch_p99_ms == pytest.approx(b.models["toy"].epoch_p99_ms)
    # Fresh offsets each epoch: the epochs differ.
    assert a.epochs[0].overall.p50_ms != pytest.approx(a.epochs[1].overall.p50_ms)


# ----------------------------------------------------------------------------- real engine, toy model

def test_light_load_meets_every_deadline(toy):
    host = EngineHost(engine_factory("monolithic", served(toy, 300)), label="mono")
    res = simulate(host, [RobotGroup("toy", 2, 10.0)], SimConfig(epochs=2, duration_s=0.5, drain_s=0.5))
    s = res.models["toy"]
    assert s.sent == 20 and s.ok == 20 and s.misses == 0
    assert s.slo_attainment == 1.0 and res.overall.slo_attainment == 1.0
    assert len(s.epoch_slo_attainment) == 2
    # End to end includes the WiFi 7 model: two 64x64x3 images up and the chunk down, >= 5 ms of base latency.
    assert 5.0 < s.p50_ms <= s.p99_ms < 300
    assert res.submit_lag_max_ms < 50
    assert set(res.to_dict()) >= {"models", "overall", "epochs", "submit_lag_max_ms"}


def test_deadline_below_model_latency_misses_everything(toy):
    host = EngineHost(engine_factory("monolithic", served(toy, 0.2)), label="mono")
    res = simulate(host, [RobotGroup("toy", 3, 10.0)], SimConfig(epochs=1, duration_s=0.4, drain_s=0.3,
                                                                  network="none"))
    s = res.models["toy"]
    assert s.sent > 0 and s.met == 0 and s.misses == s.sent and s.slo_attainment == 0.0
    assert s.late + sum(s.errors.values()) + s.no_reply == s.sent  # late replies or shed as expired


def test_unanswered_requests_are_misses(toy):
    cfg = EngineConfig(max_batch=1)
    res = simulate(lambda sink: BlackHoleEngine(served(toy, 100), cfg, CPU, sink), [RobotGroup("toy", 2, 10.0)],
                   SimConfig(epochs=1, duration_s=0.3, drain_s=0.1))
    s = res.models["toy"]
    assert s.sent > 0 and s.no_reply == s.sent and s.misses == s.sent and s.slo_attainment == 0.0
    assert math.isnan(s.p99_ms) and res.to_dict()["models"]["toy"]["p99_ms"] is None


class FixedFailuresEngine(Engine):
    """Answers each request at once, failing the first ``failures[epoch]`` of each epoch (one run() per epoch)."""

    def __init__(self, models, cfg, device, on_results, failures: list[int]):
        super().__init__(models, cfg, device, on_results)
        self.failures = failures
        self.epoch, self.seen = -1, 0

    def run(self, stop) -> None:
        self.epoch, self.seen = self.epoch + 1, 0
        super().run(stop)

    def step(self) -> bool:
        _, batch, _ = self.queues.take(self.cfg.max_batch)
        io = self.models["toy"].model.io
        results = []
        for r in batch:
            self.seen += 1
            fail = self.seen <= self.failures[self.epoch]
            results.append(Result(r, error=(ErrorCode.INTERNAL, "injected")) if fail
                           else Result(r, actions=np.zeros((io.horizon, io.action_dim), np.float32)))
        if results:
            self.on_results(results)
        return bool(batch)


@pytest.mark.parametrize("early_stop", [False, True])
def test_a_point_exactly_at_the_target_passes(toy, early_stop):
    """100 requests an epoch, attainments 0.95, 0.98, 1.0, 0.97, 1.0: a mean of exactly 0.98, which the float sum makes
    0.9799999999999999. The point failed at a 0.98 target, and the early stop ended it after 4 epochs, its best
    possible mean (3.9 + 1) / 5 computed as below 0.98."""
    cfg = EngineConfig(max_batch=1, shed_expired=False)
    host = EngineHost(lambda sink: FixedFailuresEngine(served(toy, 1000), cfg, CPU, sink, [5, 2, 0, 3, 0]))
    p = measure_point(host, "toy", 1, 100.0, SimConfig(epochs=5, duration_s=1.0, drain_s=0.0, network="none"), 0.98,
                      early_stop=early_stop)
    assert p.epoch_slo_attainment == [0.95, 0.98, 1.0, 0.97, 1.0], p.epoch_slo_attainment
    assert p.epochs == 5 and p.passed


def test_a_late_answer_from_an_earlier_run_is_not_this_runs_answer(toy):
    # An engine reused across points (a worker process, say) answers the first run's requests only once the
    # second run has begun. Those answers must not count for the second run's requests of the same number.
    class Straggler(Engine):
        def __init__(self, *args):
            super().__init__(*args)
            self.held: list = []
            self.runs = 0

        def run(self, stop):
            self.runs += 1
            super().run(stop)

        def step(self) -> bool:
            if self.runs > 1 and self.held:
                late, self.held = self.held, []
                self.on_results([Result(r, actions=np.zeros((1, 1), np.float32), done=time.monotonic())
                                 for r in late])
            _, batch, _ = self.queues.take(self.cfg.max_batch)
            if self.runs == 1:
                self.held += batch
            return bool(batch)

    cfg = EngineConfig(max_batch=4)
    host = EngineHost(lambda sink: Straggler(served(toy, 100), cfg, CPU, sink))
    workload, sim = [RobotGroup("toy", 2, 10.0)], SimConfig(epochs=1, duration_s=0.3, drain_s=0.1, network="none")
    first = simulate(host, workload, sim).models["toy"]
    assert first.sent > 0 and first.no_reply == first.sent
    assert host.engine.held, "the first run's requests are held for the second"
    second = simulate(host, workload, sim).models["toy"]
    assert not host.engine.held, "the late answers were delivered during the second run"
    assert second.sent > 0 and second.no_reply == second.sent and second.slo_attainment == 0.0


def test_requests_still_queued_at_the_end_are_answered_as_errors(toy):
    # An engine that never steps: stopping it answers the queue with UNAVAILABLE, which counts as a miss.
    class Idle(Engine):
        def step(self) -> bool:
            return False

    cfg = EngineConfig(max_batch=1)
    res = simulate(lambda sink: Idle(served(toy, 100), cfg, CPU, sink), [RobotGroup("toy", 2, 10.0)],
                   SimConfig(epochs=1, duration_s=0.3, drain_s=0.1))
    s = res.models["toy"]
    assert s.errors == {"UNAVAILABLE": s.sent} and s.slo_attainment == 0.0



class _Delayed(Engine):
    """Answers each batch after ``delay_s`` of real time; ``late_stamp``: stamps the result before the delay, as an
    engine that hands results over after it stamped them would."""

    def __init__(self, models, cfg, device, on_results, delay_s: float, late_stamp: bool):
        super().__init__(models, cfg, device, on_results)
        self.delay_s, self.late_stamp = delay_s, late_stamp

    def step(self) -> bool:
        _, batch, _ = self.queues.take(self.cfg.max_batch)
        if not batch:
            return False
        stamped = time.monotonic()
        time.sleep(self.delay_s)
        io = self.models[batch[0].model].model.io
        done = stamped if self.late_stamp else time.monotonic()
        self.on_results([Result(r, actions=np.zeros((io.horizon, io.action_dim), np.float32), done=done)
                         for r in batch])
        return True


def test_reply_time_is_when_the_harness_has_the_reply(toy):
    cfg = EngineConfig(max_batch=4, shed_expired=False)
    res = simulate(lambda sink: _Delayed(served(toy, 500), cfg, CPU, sink, 0.04, late_stamp=True),
                   [RobotGroup("toy", 2, 5.0)], SimConfig(epochs=1, duration_s=0.4, drain_s=0.3, network="none"))
    s = res.models["toy"]
    assert s.ok == s.sent > 0 and s.p50_ms >= 39  # not the engine's stamp, 40 ms earlier


def test_the_epoch_waits_out_the_deadline_of_its_last_request(toy):
    # A drain shorter than the deadline must not stop the engine on requests that can still be answered in time.
    cfg = EngineConfig(max_batch=4, shed_expired=False)
    res = simulate(lambda sink: _Delayed(served(toy, 400), cfg, CPU, sink, 0.08, late_stamp=False),
                   [RobotGroup("toy", 3, 10.0)], SimConfig(epochs=2, duration_s=0.3, drain_s=0.0, network="none"))
    s = res.models["toy"]
    assert s.sent > 0 and s.errors == {} and s.met == s.sent and s.slo_attainment == 1.0


def test_robot_groups_refuse_rates_that_send_nothing():
    for hz in (0.0, -2.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="hz > 0"):
            RobotGroup("toy", 2, hz)
    with pytest.raises(ValueError, match="robots >= 0"):
        RobotGroup("toy", -1, 2.0)


def test_a_reused_engine_takes_requests_before_its_thread_gets_going(toy):
    # The previous epoch's finish closes the queues (a submit after an engine stopped is refused
    # UNAVAILABLE); the host reopens them before the next epoch, not only the engine's thread, which
    # may start late: the robots' first requests of the epoch must still be served.
    class LateStart(QueueModelEngine):
        def run(self, stop) -> None:
            time.sleep(0.15)
            super().run(stop)

    cfg = EngineConfig(max_batch=1, shed_expired=False)
    host = EngineHost(lambda sink: LateStart(served(toy, 1000), cfg, CPU, sink, 0.001), reuse=True)
    res = simulate(host, [RobotGroup("toy", 4, 10.0)], SimConfig(epochs=2, duration_s=0.3, drain_s=0.3))
    s = res.models["toy"]
    assert s.sent > 0 and s.errors == {} and s.ok == s.sent and s.slo_attainment == 1.0

# ----------------------------------------------------------------------------- capacity search

def _point(n: int, passed: bool) -> Point:
    return Point(robots=n, slo_attainment=1.0 if passed else 0.5, p50_ms=1, p99_ms=1, passed=passed, epochs=1,
                 sent=1, misses=0, errors={}, no_reply=0, submit_lag_max_ms=0, wall_s=0)


@pytest.mark.parametrize("threshold,start,max_robots", [(37, 1, 256), (0, 1, 64), (64, 4, 64), (5, 8, 100)])
def test_search_finds_a_monotone_threshold(threshold, start, max_robots):
    s = CapacitySearch(0.98, start, max_robots)
    while not s.done:
        n = s.next()
        s.record(_point(n, n <= threshold))
    assert s.capacity == min(threshold, max_robots)
    assert len(s.points) <= 2 * math.ceil(math.log2(max_robots)) + 2
    assert len({p.robots for p in s.points}) == len(s.points)


def test_search_bisects_between_the_largest_pass_and_the_smallest_failure():
    s = CapacitySearch(0.98, 1, 64)
    outcomes = {1: True, 2: True, 4: True, 8: True, 16: False, 12: True, 14: False, 13: True}
    while not s.done:
        n = s.next()
        s.record(_point(n, outcomes[n]))
    assert s.capacity == 13 and [p.robots for p in s.points] == [1, 2, 4, 8, 16, 12, 14, 13]


def _run_screened(s: CapacitySearch, passes) -> list[tuple[int, int]]:
    """Drive a screened search; ``passes(n, epochs)`` decides each point. Returns (robots, epochs) in order."""
    trace = []
    while not s.done:
        n, epochs = s.next(), s.epochs_next() or s.full_epochs
        trace.append((n, epochs))
        p = _point(n, passes(n, epochs))
        p.epochs = epochs
        s.record(p)
    return trace


@pytest.mark.parametrize("threshold", [1, 37, 63, 64])
def test_screened_search_runs_every_epoch_only_on_the_candidate(threshold):
    s = CapacitySearch(0.98, 8, 64, screen_epochs=1, full_epochs=5)
    trace = _run_screened(s, lambda n, epochs: n <= threshold)
    assert s.capacity == threshold
    # Full runs only at the bracket's ends: the answer, and the count above it (none above max_robots).
    assert [t for t in trace if t[1] == 5] == [(threshold, 5)] + [(threshold + 1, 5)] * (threshold < 64)
    assert all(e == 1 for _, e in trace[:-2])


def test_screened_search_goes_on_above_a_screening_failure_that_passes_its_full_run():
    # One short epoch at 11, 12 and 16 drew hard phases; with every epoch they pass, up to 40.
    s = CapacitySearch(0.98, 8, 256, screen_epochs=1, full_epochs=5)
    trace = _run_screened(s, lambda n, epochs: n <= 40 if epochs == 5 else n <= 10 or 17 <= n <= 40)
    assert s.capacity == 40
    full = [n for n, e in trace if e == 5]
    assert full[:2] == [10, 11] and full[-2:] == [40, 41]
    assert all(n <= 40 for n, e in trace if e == 5 and n != 41)


def test_screened_search_goes_on_below_a_candidate_that_fails_its_full_run():
    # Short runs pass up to 40, but with every epoch only up to 33 holds: the full-run failure wins,
    # and from then on every point runs all epochs (galloping down 39, 37, 33, then bisecting).
    s = CapacitySearch(0.98, 8, 256, screen_epochs=1, full_epochs=5)
    trace = _run_screened(s, lambda n, epochs: n <= (40 if epochs == 1 else 33))
    assert s.capacity == 33
    first_full = next(i for i, (_, e) in enumerate(trace) if e == 5)
    assert trace[first_full] == (40, 5) and all(e == 5 for _, e in trace[first_full:])
    assert [n for n, _ in trace[first_full:]] == [40, 39, 37, 33, 35, 34]


@pytest.mark.parametrize("start,max_robots,screen_ok,full_ok", [(32, 256, 82, 18), (4, 16, 6, 2), (1, 64, 3, 1)])
def test_screened_search_gallops_down_to_one_robot_if_it_must(start, max_robots, screen_ok, full_ok):
    s = CapacitySearch(0.98, start, max_robots, screen_epochs=1, full_epochs=5)
    _run_screened(s, lambda n, epochs: n <= (screen_ok if epochs == 1 else full_ok))
    assert s.capacity == full_ok


def test_screened_search_where_no_full_run_passes_ends_at_zero():
    s = CapacitySearch(0.98, 4, 16, screen_epochs=1, full_epochs=5)
    _run_screened(s, lambda n, epochs: epochs == 1 and n <= 6)
    assert s.capacity == 0 and s.done


def test_screened_search_with_nothing_passing_confirms_the_failure_at_one_robot():
    s = CapacitySearch(0.98, 4, 64, screen_epochs=1, full_epochs=5)
    trace = _run_screened(s, lambda n, epochs: False)
    assert s.capacity == 0 and trace == [(4, 1), (2, 1), (1, 1), (1, 5)]


def test_screening_needs_fewer_epochs_than_a_full_point():
    with pytest.raises(ValueError, match="screen_epochs"):
        CapacitySearch(0.98, 1, 64, screen_epochs=5, full_epochs=5)


def test_sweep_capacity_stops_at_the_first_failure():
    s = SweepSearch([8, 2, 4, 16])
    for n, ok in [(2, True), (4, True), (8, False), (16, True)]:
        assert s.next() == n
        s.record(_point(n, ok))
    assert s.done and s.capacity == 4


def test_capacity_search_finds_the_analytic_threshold():
    """Service S per request at max_batch 1, robots at f: capacity = floor(1 / (S f)).

    Up to that count the work arriving in any period fits in it, so no request waits more
    than n S <= 1/f = the deadline; one robot more and the backlog grows without bound.
    """
    toy = build_model("toy", "tiny")
    hz, expect = 40.0, 10
    service = 1.0 / (hz * (expect + 0.2))
    host = EngineHost(queue_model_factory(toy, 1e3 / hz, service), label="fake")
    res = find_capacity(host, "toy", hz, SimConfig(epochs=1, duration_s=0.6, drain_s=0.2, network="none"),
                        max_robots=32, progress=False)
    assert res.capacity == expect
    tried = {p.robots: p for p in res.points}
    assert tried[expect].passed and tried[expect].slo_attainment == 1.0
    assert not tried[expect + 1].passed
    assert len(host.prepare_s) == 1  # one engine, reused for every point


def test_compare_sweeps_engines_side_by_side_and_rebuilds_without_reuse():
    toy = build_model("toy", "tiny")
    hz = 40.0
    fast = EngineHost(queue_model_factory(toy, 25, 1 / (hz * 8.2)), label="fast")
    slow = EngineHost(queue_model_factory(toy, 25, 1 / (hz * 4.2)), reuse=False, label="slow")
    seen: list[tuple[str, int]] = []
    out = compare_capacity({"fast": fast, "slow": slow}, "toy", hz,
                           SimConfig(epochs=1, duration_s=0.5, drain_s=0.2, network="none"),
                           robots=[4, 6, 8], progress=False, on_point=lambda e, p: seen.append((e, p.robots)))
    assert out["fast"].capacity == 8 and out["slow"].capacity == 4
    assert seen == [("fast", 4), ("slow", 4), ("fast", 6), ("slow", 6), ("fast", 8), ("slow", 8)]
    assert len(fast.prepare_s) == 1 and len(slow.prepare_s) == 3


def test_sweep_runs_every_epoch_of_a_failing_point():
    toy = build_model("toy", "tiny")
    res = sweep(queue_model_factory(toy, 25, 1 / (40 * 2.2)), "toy", [6], 40.0,
                SimConfig(epochs=2, duration_s=0.3, drain_s=0.1, network="none"), progress=False)
    assert res.points[0].epochs == 2 and not res.points[0].passed and res.capacity == 0


def test_engine_factory_rejects_unknown_config_fields(toy):
    with pytest.raises(ValueError, match="no field"):
        engine_factory("monolithic", served(toy, 100), no_such_field=1)


# ----------------------------------------------------------------------------- CLI

def test_cli_writes_capacity_json_and_plot(tmp_path):
    out, png = tmp_path / "cap.json", tmp_path / "cap.png"
    cmd = [sys.executable, os.path.join(ROOT, "bench", "capacity.py"), "--models", "toy", "--engines",
           "monolithic,rr=monolithic:policy=rr", "--size", "tiny", "--device", "cpu", "--hz", "10", "--epochs", "1",
           "--duration", "0.3", "--drain", "0.3", "--sweep", "1,2", "--deadline", "toy=500", "--out", str(out),
           "--plot", str(png), "--quiet"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(out.read_text())
    assert doc["schema"] == "robion.capacity/1" and doc["target"] == 0.98
    assert doc["capacity"] == {"toy": {"monolithic": 2, "rr": 2}}
    # Both passed the sweep's largest count: lower bounds, so no ratio.
    assert doc["capped"] == {"toy": {"monolithic": True, "rr": True}}
    assert doc["ratios"] == {"toy": {"rr/monolithic": None}}
    assert doc["complete"] == {"toy": {"monolithic": True, "rr": True}}
    assert doc["deadlines_ms"] == {"toy": 500.0}
    bound = doc["overlap_bound"]["toy"]
    assert bound["batch"] == 2 and bound["vlm_ms"] > 0 and bound["action_ms"] > 0
    assert abs(bound["bound"] - (bound["vlm_ms"] + bound["action_ms"]) / max(bound["vlm_ms"], bound["action_ms"])) < 1e-9
    assert 1.0 < bound["bound"] <= 2.0
    for engine in ("monolithic", "rr"):
        pts = doc["curves"]["toy"][engine]
        assert [p["robots"] for p in pts] == [1, 2]
        assert {"slo_attainment", "p50_ms", "p99_ms", "passed", "epochs", "sent", "misses",
                "submit_lag_max_ms"} <= set(pts[0])
    assert doc["settings"]["engines"]["rr"] == {"kind": "monolithic", "max_batch": 2, "policy": "rr"}
    assert {"gpu", "date", "commit", "command", "torch"} <= set(doc["meta"])
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        assert not png.exists()
    else:
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_sweep_runs_every_epoch_and_records_what_it_did(tmp_path):
    out = tmp_path / "sweep.json"
    cmd = [sys.executable, os.path.join(ROOT, "bench", "capacity.py"), "--models", "toy", "--engines", "monolithic",
           "--size", "tiny", "--device", "cpu", "--hz", "10", "--epochs", "2", "--duration", "0.3", "--drain", "0.1",
           "--sweep", "1", "--deadline", "toy=1", "--quiet", "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(out.read_text())
    point = doc["curves"]["toy"]["monolithic"][0]
    assert not point["passed"] and point["epochs"] == 2 and len(point["epoch_slo_attainment"]) == 2
    assert doc["settings"]["early_stop"] is False and doc["settings"]["screen_epochs"] is None


@pytest.mark.parametrize("args,message", [
    (["--hz", "0"], "--hz: expected a positive rate"),
    (["--hz", "-2"], "--hz: expected a positive rate"),
    (["--hz", "2", "--duration", "0.3"], "--duration: expected at least one period"),
    (["--epochs", "0"], "--epochs: expected at least 1"),
    (["--drain", "-1"], "--drain: expected a non-negative"),
    (["--sweep", "0,1"], "--sweep: expected robot counts of at least 1"),
    (["--start", "9", "--max-robots", "4"], "expected 1 <= start <= max-robots"),
    (["--target", "1.5"], "--target: expected a share"),
    (["--seed", "-1"], "--seed: expected a non-negative integer"),
    ([], "no deadline for toy"),  # the toy is no paper model: it raised ValueError after the engines were built
    # tracebacks, some only after the models were built and the overlap bound measured
    (["--sweep", "1.5"], "--sweep: expected comma-separated robot counts"),
    (["--network", "lte"], "--network: expected one of wifi7"),
    (["--size", "huge"], "--size: toy has no size 'huge'"),
    (["--log-level", "chatty"], "--log-level: expected one of debug"),
])
def test_cli_refuses_bad_measurement_arguments_before_building_models(args, message, capsys):
    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import capacity as bench_capacity

    with pytest.raises(SystemExit) as exc:
        bench_capacity.main(["--models", "toy", "--size", "tiny", "--device", "cpu", *args])
    assert exc.value.code == 2 and message in capsys.readouterr().err


@pytest.mark.parametrize("args,message", [
    # measured, each to a capacity of 0 written with exit 0
    (["--engines", "m=monolithic:max_batch=0"], "engine.max_batch: expected a power of two"),
    (["--max-batch", "3"], "engine.max_batch: expected a power of two"),
    (["--engines", "bogus"], "engine.kind: expected one of"),
    (["--deadline", "toy=-5"], "--deadline 'toy=-5': expected name=ms with a positive number"),
    (["--deadline", "toy=nan"], "--deadline 'toy=nan': expected name=ms with a positive number"),
    (["--deadline", "toy=abc"], "--deadline 'toy=abc': expected name=ms with a positive number"),
    (["--models", "nope", "--deadline", "nope=100"], "--models nope: unknown architecture 'nope'"),
])
def test_cli_refuses_engines_and_deadlines_a_cluster_would_refuse(args, message, capsys):
    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import capacity as bench_capacity

    argv = ["--models", "toy", "--size", "tiny", "--device", "cpu", "--deadline", "toy=100", *args]
    if "--models" in args:
        argv = argv[argv.index("--device"):]
    with pytest.raises(SystemExit) as exc:
        bench_capacity.main(argv)
    shown = str(exc.value.code) + capsys.readouterr().err
    assert exc.value.code != 0 and message in shown, shown


def test_merged_results_drop_ratios_of_a_rerun_without_its_baseline(tmp_path):
    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import capacity as bench_capacity
    from services.executor.simulation import CapacityResult

    def result(engine: str, capacity: int) -> CapacityResult:
        return CapacityResult("toy", engine, 0.98, "search", capacity, [], [])

    path = tmp_path / "cap.json"
    first = bench_capacity.Report(path, {"target": 0.98}, {}, merge=False)
    first.model_done("toy", {"monolithic": result("monolithic", 4), "rr": result("rr", 4)}, "monolithic")
    assert json.loads(path.read_text())["ratios"] == {"toy": {"rr/monolithic": 1.0}}
    again = bench_capacity.Report(path, {"target": 0.98}, {}, merge=True)
    again.model_done("toy", {"rr": result("rr", 0)}, None)
    doc = json.loads(path.read_text())
    assert doc["capacity"] == {"toy": {"rr": 0}} and doc["ratios"] == {}


def test_cli_meta_names_the_shipped_commit_and_replot_needs_a_png(tmp_path, monkeypatch):
    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import capacity as bench_capacity

    monkeypatch.setenv("ROBION_COMMIT", "0123abcd")
    assert bench_capacity.meta("cpu")["commit"] == "0123abcd"
    doc = tmp_path / "cap.json"
    doc.write_text(json.dumps({"schema": "robion.capacity/1", "target": 0.98, "curves": {}}))
    with pytest.raises(SystemExit, match="--replot needs --plot"):
        bench_capacity.main(["--replot", str(doc)])
    with pytest.raises(SystemExit, match="no plot written"):  # no curves (or no matplotlib): nothing drawn
        bench_capacity.main(["--replot", str(doc), "--plot", str(tmp_path / "x.png")])
    with pytest.raises(SystemExit, match="--models is required"):
        bench_capacity.main([])


def test_a_merged_rerun_replaces_a_model_from_its_first_point_and_keeps_one_target(tmp_path):
    """An interrupted merged rerun left its new points on the old curve, beside the old capacities; and models
    kept from a run at another target were listed under this run's target."""
    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import capacity as bench_capacity
    from services.executor.simulation import CapacityResult, Point

    def point(robots: int, epochs: int) -> Point:
        return Point(robots=robots, slo_attainment=1.0, p50_ms=1.0, p99_ms=2.0, passed=True, epochs=epochs, sent=1,
                     misses=0, errors={}, no_reply=0, submit_lag_max_ms=0.0, wall_s=0.1)

    path = tmp_path / "cap.json"
    first = bench_capacity.Report(path, {"target": 0.98, "models": {"toy": "toy", "other": "toy"}}, {}, merge=False)
    first.point("toy", "robion", point(12, 5))
    first.point("other", "robion", point(3, 5))
    first.model_done("toy", {"robion": CapacityResult("toy", "robion", 0.98, "search", 12, [], [])}, None)
    first.model_done("other", {"robion": CapacityResult("other", "robion", 0.98, "search", 3, [], [])}, None)
    again = bench_capacity.Report(path, {"target": 0.98}, {}, merge=True)
    again.point("toy", "robion", point(1, 1))
    doc = json.loads(path.read_text())  # as an interruption here would leave it
    assert [p["robots"] for p in doc["curves"]["toy"]["robion"]] == [1]
    assert "toy" not in doc["capacity"] and doc["capacity"]["other"] == {"robion": 3}
    with pytest.raises(SystemExit, match="target 0.98"):
        bench_capacity.Report(path, {"target": 0.9}, {}, merge=True)
    # The earlier run's settings no longer claim the model measured again: one run describes each model.
    runs = json.loads(path.read_text())["runs"]
    assert [sorted(r["settings"]["models"]) for r in runs] == [["other"]]


def test_a_merge_needs_comparable_runs_and_a_model_is_claimed_from_its_first_point(tmp_path):
    """A merge of runs at another rate, network, batch, size or GPU was accepted, and the plot titled every column with
    this run's GPU. A rerun interrupted before a model's first point listed it in its own settings too, beside the
    earlier run that measured it: two runs claimed one model's results."""
    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import capacity as bench_capacity
    from services.executor.simulation import CapacityResult, Point

    base = {"target": 0.98, "hz": 2.0, "network": "wifi7", "max_batch": 2, "size": "full", "duration_s": 3}
    point = Point(robots=3, slo_attainment=1.0, p50_ms=1.0, p99_ms=2.0, passed=True, epochs=5, sent=1, misses=0,
                  errors={}, no_reply=0, submit_lag_max_ms=0.0, wall_s=0.1)
    path = tmp_path / "cap.json"
    first = bench_capacity.Report(path, {**base, "models": {"toy": "toy", "other": "toy"}}, {"gpu": "H100"}, merge=False)
    for m in ("toy", "other"):
        first.point(m, "robion", point)
        first.model_done(m, {"robion": CapacityResult(m, "robion", 0.98, "search", 3, [], [])}, None)
    for change, meta_, fragment in (({"hz": 5.0}, {"gpu": "H100"}, "hz 2.0 there, 5.0 here"),
                                    ({"network": "5g"}, {"gpu": "H100"}, "network"),
                                    ({"size": "tiny"}, {"gpu": "H100"}, "size"),
                                    ({}, {"gpu": "H200"}, "gpu 'H100' there, 'H200' here")):
        with pytest.raises(SystemExit, match=fragment):
            bench_capacity.Report(path, {**base, **change, "models": {"toy": "toy"}}, meta_, merge=True)
    # Another duration (E1 sets one per model) merges; interrupted after toy's first point, before other's.
    again = bench_capacity.Report(path, {**base, "duration_s": 4, "models": {"toy": "toy", "other": "toy"}},
                                  {"gpu": "H100"}, merge=True)
    again.point("toy", "robion", point)
    doc = json.loads(path.read_text())
    assert doc["settings"]["models"] == {"toy": "toy"}
    assert [sorted(r["settings"]["models"]) for r in doc["runs"]] == [["other"]]
    assert doc["capacity"] == {"other": {"robion": 3}}


def test_replot_of_a_missing_or_foreign_file_is_a_message(tmp_path):
    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import capacity as bench_capacity

    with pytest.raises(SystemExit, match="--replot: cannot read"):
        bench_capacity.main(["--replot", str(tmp_path / "none.json"), "--plot", str(tmp_path / "x.png")])
    (tmp_path / "e4.json").write_text(json.dumps({"rows": []}))
    with pytest.raises(SystemExit, match="is not a robion.capacity/1 file"):
        bench_capacity.main(["--replot", str(tmp_path / "e4.json"), "--plot", str(tmp_path / "x.png")])


def test_meta_does_not_call_an_unknown_tree_clean(tmp_path, monkeypatch):
    """Without git (a copy of the tree shipped without .git) the tree's state is unknown: it was recorded as
    clean, and an edited copy read as a clean build of the commit ROBION_COMMIT names."""
    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import capacity as bench_capacity

    monkeypatch.setattr(bench_capacity, "_git", lambda *args: None)
    assert bench_capacity.meta("cpu")["dirty"] is None
    monkeypatch.setenv("ROBION_COMMIT", "0123abcd")
    assert bench_capacity.meta("cpu")["dirty"] is None
    monkeypatch.setenv("ROBION_DIRTY", "1")
    assert bench_capacity.meta("cpu")["dirty"] is True
    monkeypatch.setenv("ROBION_DIRTY", "0")
    assert bench_capacity.meta("cpu")["dirty"] is False


def test_the_plot_shows_a_counts_full_run_over_its_screening(tmp_path, monkeypatch):
    """A full run stopped early after one epoch tied with the one-epoch screening point of the same count, and
    the plot kept the screening pass where the search had taken the full run's failure."""
    pytest.importorskip("matplotlib")
    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import capacity as bench_capacity
    import matplotlib.axes

    drawn = []
    real = matplotlib.axes.Axes.plot

    def spy(self, *args, **kwargs):
        if kwargs.get("label", "").startswith("robion"):
            drawn.append((list(args[0]), list(args[1])))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "plot", spy)

    def pt(robots, slo, epochs, screened):
        return {"robots": robots, "slo_attainment": slo, "p99_ms": 10.0, "epochs": epochs, "screened": screened}

    doc = {"target": 0.98, "capacity": {"toy": {"robion": 8}}, "curves": {"toy": {"robion": [
        pt(8, 0.99, 5, False), pt(9, 0.985, 1, True), pt(9, 0.85, 1, False)]}}}
    assert bench_capacity.plot(doc, tmp_path / "p.png")
    assert drawn[0] == ([8, 9], [99.0, 85.0])  # the SLO panel (the p99 panel follows)


class _NoActionsEngine(Engine):
    """Answers every request with neither actions nor an error."""

    def step(self) -> bool:
        _, batch, _ = self.queues.take(self.cfg.max_batch)
        self.on_results([Result(r) for r in batch])
        return bool(batch)


class _SubmitRaisesOnce(QueueModelEngine):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.raised = False

    def submit(self, req) -> None:
        if not self.raised:
            self.raised = True
            raise ValueError("a bug in the engine's submit")
        super().submit(req)


def test_answers_without_actions_and_failed_submits_are_misses_and_the_epoch_goes_on(toy):
    """An answer with neither actions nor an error counted as met; a submit raising anything but a protocol error
    ended the driver, and the rest of the epoch was never sent (counted unanswered, silently)."""
    cfg = EngineConfig(max_batch=1)
    res = simulate(lambda sink: _NoActionsEngine(served(toy, 500), cfg, CPU, sink), [RobotGroup("toy", 2, 10.0)],
                   SimConfig(epochs=1, duration_s=0.5, drain_s=0.1, network="none"))
    s = res.models["toy"]
    assert s.sent == 10 and s.met == 0 and s.errors == {"INTERNAL": 10}
    engine_cfg = EngineConfig(max_batch=1, shed_expired=False)
    res = simulate(lambda sink: _SubmitRaisesOnce(served(toy, 500), engine_cfg, CPU, sink, 0.001),
                   [RobotGroup("toy", 2, 10.0)], SimConfig(epochs=1, duration_s=0.5, drain_s=0.1, network="none"))
    s = res.models["toy"]
    assert s.sent == 10 and s.met == 9 and s.errors == {"INTERNAL": 1} and s.no_reply == 0


def test_an_epoch_shorter_than_one_period_is_refused(toy):
    """Its epochs sent nothing, and their NaN attainment dropped out of the mean: one request decided the point."""
    with pytest.raises(ValueError, match="shorter than one period of toy at 2 Hz"):
        simulate(queue_model_factory(toy, 500, 0.001), [RobotGroup("toy", 2, 2.0)],
                 SimConfig(epochs=2, duration_s=0.3))


class _BusyDriverEngine(QueueModelEngine):
    """Holds the GIL in its submit, as a busy Python scheduler would: the harness sends late."""

    def submit(self, req) -> None:
        end = time.monotonic() + 0.02
        while time.monotonic() < end:
            pass
        super().submit(req)


def test_a_point_the_harness_sent_late_is_flagged_and_a_capped_capacity_is_a_lower_bound(toy, tmp_path):
    cfg = EngineConfig(max_batch=1, shed_expired=False)
    sim = SimConfig(epochs=1, duration_s=0.5, drain_s=0.1, network="none")
    late = measure_point(EngineHost(lambda sink: _BusyDriverEngine(served(toy, 200), cfg, CPU, sink, 0.001)),
                         "toy", 8, 20.0, sim, 0.98)
    assert not late.lag_ok and late.submit_lag_p99_ms > 0.05 * 200 and len(late.epoch_submit_lag_p99_ms) == 1
    fine = measure_point(EngineHost(queue_model_factory(toy, 200, 0.001)), "toy", 2, 20.0, sim, 0.98)
    assert fine.lag_ok and fine.submit_lag_p99_ms < 10

    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import capacity as bench_capacity

    # As in test_capacity_search_finds_the_analytic_threshold: b holds 2 robots at 40 Hz, a more than 4.
    results = compare_capacity({"a": EngineHost(queue_model_factory(toy, 25, 0.0001), label="a"),
                                "b": EngineHost(queue_model_factory(toy, 25, 1 / (40 * 2.2)), label="b")}, "toy",
                               40.0, SimConfig(epochs=1, duration_s=0.6, drain_s=0.2, network="none"), max_robots=4,
                               progress=False)
    assert results["a"].capped and results["a"].capacity == 4
    assert not results["b"].capped and results["b"].capacity == 2
    report = bench_capacity.Report(tmp_path / "cap.json", {"target": 0.98}, {}, merge=False)
    report.model_done("toy", results, "b")
    doc = json.loads((tmp_path / "cap.json").read_text())
    assert doc["capped"] == {"toy": {"a": True, "b": False}}
    assert doc["ratios"] == {"toy": {"a/b": None}}  # a lower bound over a measurement is no ratio


class _SubmitAlwaysRaises(QueueModelEngine):
    def submit(self, req) -> None:
        raise ValueError("broken")


def test_a_submit_that_keeps_failing_logs_one_traceback_an_epoch_and_a_sweep_that_passes_is_capped(toy, caplog):
    """One traceback per request slowed the driver (400 of them in a 2 s epoch); a sweep whose every count passed
    reported its largest count as measured, and a ratio of two such lower bounds."""
    import logging

    engine_cfg = EngineConfig(max_batch=1, shed_expired=False)
    with caplog.at_level(logging.WARNING, logger="services.executor.simulation"):
        res = simulate(lambda sink: _SubmitAlwaysRaises(served(toy, 500), engine_cfg, CPU, sink, 0.001),
                       [RobotGroup("toy", 4, 20.0)], SimConfig(epochs=1, duration_s=0.5, drain_s=0.1, network="none"))
    assert res.models["toy"].errors == {"INTERNAL": 40}
    assert sum(r.exc_info is not None for r in caplog.records) == 1
    assert any("failed for 40 requests" in r.getMessage() for r in caplog.records)
    results = compare_capacity({"a": EngineHost(queue_model_factory(toy, 500, 0.0001), label="a")}, "toy", 10.0,
                               SimConfig(epochs=1, duration_s=0.3, drain_s=0.1, network="none"), robots=[1, 2],
                               progress=False)
    assert results["a"].capacity == 2 and results["a"].capped
