import threading
import time

import numpy as np
import pytest
import torch

from services.executor.engine import MonolithicEngine, ServedModel
from services.executor.scheduler import ModelQueues, Request, ServiceTimes, batch_size_for
from shared.config import EngineConfig
from shared.models import build_model
from shared.protocol import ErrorCode, ProtocolError


def req(model: str, rid: str, arrival: float, deadline: float, shape=(2, 64, 64, 3), state_dim=8, prompt_len=16) -> Request:
    return Request(id=rid, robot="r", model=model, images=np.zeros(shape, np.uint8),
                   state=np.zeros(state_dim, np.float32), tokens=np.zeros(prompt_len, np.int64),
                   arrival=arrival, deadline=deadline)


@pytest.mark.parametrize("pending,max_batch,expected", [(0, 2, 0), (1, 2, 1), (2, 2, 2), (3, 2, 2), (3, 4, 2),
                                                        (5, 4, 4), (7, 8, 4), (8, 8, 8), (1, 1, 1), (9, 1, 1)])
def test_batch_size_is_largest_power_of_two(pending, max_batch, expected):
    assert batch_size_for(pending, max_batch) == expected


def test_esf_picks_head_closest_to_deadline():
    q = ModelQueues(["a", "b"], policy="esf", shed_expired=False)
    q.put(req("a", "a1", 0.0, 100.0))
    q.put(req("b", "b1", 1.0, 50.0))  # arrived later, tighter deadline
    model, batch, _ = q.take(2, now=2.0)
    assert model == "b" and [r.id for r in batch] == ["b1"]


def test_rr_alternates_and_lqf_prefers_longer_queue():
    rr = ModelQueues(["a", "b"], policy="rr", shed_expired=False)
    for i in range(4):
        rr.put(req("a", f"a{i}", i, 1e9))
        rr.put(req("b", f"b{i}", i, 1e9))
    order = [rr.take(1, now=0)[0] for _ in range(4)]
    assert order in (["a", "b", "a", "b"], ["b", "a", "b", "a"])
    lqf = ModelQueues(["a", "b"], policy="lqf", shed_expired=False)
    lqf.put(req("a", "a0", 0, 1e9))
    for i in range(3):
        lqf.put(req("b", f"b{i}", 1 + i, 1e9))
    assert lqf.take(2, now=0)[0] == "b"


def test_queue_bound_and_unknown_model_and_shedding():
    q = ModelQueues(["a"], max_queue=2)
    q.put(req("a", "1", 0, 10))
    q.put(req("a", "2", 0, 10))
    with pytest.raises(ProtocolError) as e:
        q.put(req("a", "3", 0, 10))
    assert e.value.code == ErrorCode.OVERLOADED
    with pytest.raises(ProtocolError) as e:
        q.put(req("zzz", "4", 0, 10))
    assert e.value.code == ErrorCode.UNKNOWN_MODEL
    model, batch, expired = q.take(2, now=11)
    assert batch == [] and [r.id for r in expired] == ["1", "2"]


def test_monolithic_engine_serves_batches_equal_to_eager():
    model = build_model("toy", seed=1)
    results = []
    done = threading.Event()

    def sink(rs):
        results.extend(rs)
        if len(results) >= 5:
            done.set()

    eng = MonolithicEngine({"toy": ServedModel("toy", model, 1.0)}, EngineConfig(max_batch=2), torch.device("cpu"), sink)
    eng.prepare()
    rng = np.random.default_rng(0)
    now = time.monotonic()
    reqs = []
    for i in range(5):
        r = req("toy", str(i), now, now + 60)
        r.images = rng.integers(0, 256, r.images.shape, dtype=np.uint8)
        r.state = rng.standard_normal(8).astype(np.float32)
        r.noise = rng.standard_normal((10, 7)).astype(np.float32)
        reqs.append(r)
        eng.submit(r)
    stop = threading.Event()
    t = threading.Thread(target=eng.run, args=(stop,))
    t.start()
    assert done.wait(30)
    stop.set()
    t.join(10)
    assert sorted(r.request.id for r in results) == [str(i) for i in range(5)]
    for res in results:
        r = res.request
        with torch.inference_mode():
            ref = model.action_stage(model.vlm_stage(torch.from_numpy(r.images)[None], torch.from_numpy(r.state)[None],
                                                     torch.from_numpy(r.tokens)[None]), torch.from_numpy(r.noise)[None])[0]
        np.testing.assert_allclose(res.actions, ref.numpy(), rtol=1e-4, atol=1e-5)


def test_a_refused_request_does_not_use_up_noise():
    """The engine draws each request's initial noise from a per-model seeded sequence, in the
    order requests are accepted: a request refused as OVERLOADED must not take a draw, or every
    later request's actions would differ from a run without that refusal."""
    model = build_model("toy", seed=1)

    def accepted_noise(refuse_one: bool) -> np.ndarray:
        eng = MonolithicEngine({"toy": ServedModel("toy", model, 1.0)}, EngineConfig(max_batch=2, max_queue=1),
                               torch.device("cpu"), lambda rs: None)
        now = time.monotonic()
        eng.submit(req("toy", "a", now, now + 60))
        if refuse_one:
            with pytest.raises(ProtocolError) as exc:
                eng.submit(req("toy", "refused", now, now + 60))
            assert exc.value.code == ErrorCode.OVERLOADED
        eng.queues.drain()
        second = req("toy", "b", now, now + 60)
        eng.submit(second)
        return second.noise

    np.testing.assert_array_equal(accepted_noise(True), accepted_noise(False))


def test_service_times_estimate_is_a_high_quantile_of_a_recent_window():
    t = ServiceTimes()
    assert t.estimate(0.0) == 0.0  # nothing measured yet: nothing may be shed for lateness
    for ms in range(1, 11):
        t.note(ms / 1e3, now=1.0)
    assert t.estimate(1.0) == pytest.approx(0.010)  # p90 of 1..10 ms: the 10th value at index 9
    for _ in range(ServiceTimes.WINDOW):
        t.note(0.002, now=1.0)  # the engine got faster (a lighter co-located model): the old times age out
    assert t.estimate(1.0) == pytest.approx(0.002)
    assert t.estimate(1.0 + ServiceTimes.STALE_S + 0.1) == 0.0  # no reply for a while: measured afresh


def test_a_slow_burst_ages_out_of_the_estimate_while_replies_keep_coming():
    """The window expired only after STALE_S without any reply: after a burst of 49 ms batches, the 20 ms ones that
    followed kept it alive, and the p90 stayed at 49 ms (shedding requests a 50 ms deadline could meet) until 58 new
    measurements had pushed the old ones out, about 5 s at the trickle it let through."""
    t = ServiceTimes()
    for i in range(ServiceTimes.WINDOW):
        t.note(0.049, now=i * 0.005)
    for i in range(30):  # 20 replies a second for the next 1.5 s
        t.note(0.020, now=0.4 + i * 0.05)
    assert t.estimate(0.4 + 29 * 0.05) == pytest.approx(0.020)


def test_one_slow_batch_among_few_replies_does_not_set_the_estimate():
    """Expired one by one, at 5 batches a second only the last second's five counted, and their 90th percentile is
    their slowest: one 45 ms batch among 20 ms ones shed requests with 40 ms left for a whole second."""
    t = ServiceTimes()
    for i in range(50):
        t.note(0.020, now=i * 0.2)
    t.note(0.045, now=10.0)
    assert t.estimate(10.1) == pytest.approx(0.020)
    assert t.estimate(10.0 + ServiceTimes.STALE_S + 0.1) == 0.0  # no reply since: measured afresh


def test_shed_late_never_sheds_for_an_estimate_no_request_could_beat():
    """After a stall the estimate can exceed a model's whole deadline. Shedding every request would then
    keep it there (no batch runs, nothing is measured): such an estimate sheds nothing, the requests run
    and their measurements bring it back down."""
    q = ModelQueues(["a"], policy="esf", shed_late=True)
    q.note_service("a", 0.200, now=0.0)  # one very slow batch; the requests' whole budget is 100 ms
    q.put(req("a", "runs", 0.5, 0.6))
    model, batch, shed = q.take(2, now=0.5)
    assert model == "a" and [r.id for r in batch] == ["runs"] and shed == []
    for _ in range(ServiceTimes.WINDOW):
        q.note_service("a", 0.040, now=0.6)  # measured again: 40 ms
    q.put(req("a", "hopeless", 0.55, 0.65))  # 20 ms left at 0.63, 40 ms needed: now it is shed
    q.put(req("a", "fresh", 0.62, 0.72))
    model, batch, shed = q.take(2, now=0.63)
    assert [r.id for r in shed] == ["hopeless"] and [r.id for r in batch] == ["fresh"]


@pytest.mark.parametrize("shed_late", [False, True])
def test_peek_passes_over_the_heads_take_would_shed(shed_late):
    """The engine copies the peeked batch's observations while the GPU is busy; a late head made it another batch than
    the one taken (a1, a2 against a2, a3), which was then copied again between locksteps."""
    q = ModelQueues(["a", "b"], policy="esf", shed_late=shed_late)
    if shed_late:
        q.note_service("a", 0.030, now=1.0)
    q.put(req("a", "a1", 0.0, 1.020 if shed_late else 0.5))  # late at t=1.0 (or cannot make it)
    q.put(req("a", "a2", 0.5, 1.6))
    q.put(req("a", "a3", 0.6, 1.7))
    q.put(req("b", "b1", 0.7, 1.65))
    peeked = q.peek(2, now=1.0)
    model, batch, shed = q.take(2, now=1.0)
    assert [r.id for r in shed] == ["a1"]
    assert (peeked[0], [r.id for r in peeked[1]]) == (model, [r.id for r in batch]) == ("a", ["a2", "a3"])
    assert q.peek(2, now=1.0)[0] == "b"  # and peek still takes nothing
    assert q.peek(2, now=2.0) == ("", [])  # everything left would be shed
    assert q.depths() == {"a": 0, "b": 1}


def test_shed_late_drops_heads_that_cannot_finish_in_time():
    q = ModelQueues(["a", "b"], policy="esf", shed_late=True)
    q.note_service("a", 0.030, now=1.0)
    q.put(req("a", "a-hopeless", 0.0, 1.020))  # 20 ms left at t=1.0, service takes 30: cannot be met
    q.put(req("a", "a-ok", 0.1, 1.050))  # 50 ms left: can
    q.put(req("b", "b-tight", 0.0, 1.010))  # b has no measured service time yet: kept until it expires
    model, batch, shed = q.take(2, now=1.0)
    assert [r.id for r in shed] == ["a-hopeless"]
    assert model == "b" and [r.id for r in batch] == ["b-tight"]
    assert q.service_estimate("a", now=1.0) == pytest.approx(0.030) and q.service_estimate("b", now=1.0) == 0.0
    # Without shed_late the same measurement changes nothing: only requests already late are shed.
    plain = ModelQueues(["a"], policy="esf")
    plain.note_service("a", 0.030, now=1.0)
    plain.put(req("a", "a-hopeless", 0.0, 1.020))
    assert [r.id for r in plain.take(2, now=1.0)[1]] == ["a-hopeless"] and plain.service_estimate("a") == 0.0


def test_engine_with_shed_late_answers_a_hopeless_request_deadline_exceeded_at_once(monkeypatch):
    """The real engine measures its own service time from the batches it answers, then refuses a
    request whose deadline is nearer than that, before it costs GPU time, with a message that says why."""
    monkeypatch.setattr(ServiceTimes, "STALE_S", 60.0)  # a slow test machine must not age the measurements out
    model = build_model("toy", seed=1)
    results: list = []
    arrived = threading.Condition()

    def sink(rs):
        with arrived:
            results.extend(rs)
            arrived.notify_all()

    def wait_for(n: int) -> None:
        with arrived:
            assert arrived.wait_for(lambda: len(results) >= n, timeout=30)

    eng = MonolithicEngine({"toy": ServedModel("toy", model, 1.0)}, EngineConfig(max_batch=2, shed_late=True),
                           torch.device("cpu"), sink)
    eng.prepare()
    stop = threading.Event()
    t = threading.Thread(target=eng.run, args=(stop,))
    t.start()
    try:
        for i in range(4):
            now = time.monotonic()
            eng.submit(req("toy", f"warm{i}", now, now + 60))
            wait_for(i + 1)
    finally:
        stop.set()
        t.join(10)
    estimate = eng.queues.service_estimate("toy")
    assert estimate > 0 and all(r.actions is not None for r in results)
    # One step on this thread right after the submit, so the request is still short of its deadline when taken.
    eng.queues.reopen()  # the loop's finish closed the queues; from here the test is the engine's loop
    eng.queues.note_service("toy", estimate)  # a new run starts its window afresh: the one measured above, again
    now = time.monotonic()
    # It waited (arrived an estimate ago) and is due before a batch can finish: could have made it, cannot now.
    eng.submit(req("toy", "hopeless", now - estimate, now + estimate / 2))
    assert eng.step() and len(results) == 5
    last = results[-1]
    assert last.request.id == "hopeless" and last.actions is None
    assert last.error[0] == ErrorCode.DEADLINE_EXCEEDED and "cannot be met" in last.error[1], last.error


def test_a_queue_full_of_late_requests_takes_a_fresh_one_and_answers_the_late_at_the_next_take():
    """Expired requests left the queue only at take(): during a long lockstep or a stall, a queue full of requests
    already past their deadline refused fresh ones that could still make it (OVERLOADED)."""
    q = ModelQueues(["a"], max_queue=2)
    now = time.monotonic()
    q.put(req("a", "old1", now - 1.0, now - 0.5))
    q.put(req("a", "old2", now - 1.0, now - 0.5))
    q.put(req("a", "fresh", now, now + 60.0))
    assert q.depths() == {"a": 1} and q.wait(0.0)
    model, batch, expired = q.take(2)
    assert [r.id for r in batch] == ["fresh"] and sorted(r.id for r in expired) == ["old1", "old2"]
    # The shed ones left the pending count once: an empty queue takes nothing and waits for nothing.
    assert q.take(2) == ("", [], []) and not q.wait(0.0)
    q.put(req("a", "next", now, now + 60.0))
    assert [r.id for r in q.take(2)[1]] == ["next"]
    without = ModelQueues(["a"], max_queue=1, shed_expired=False)  # nothing is shed: full is full
    without.put(req("a", "old", now - 1.0, now - 0.5))
    with pytest.raises(ProtocolError) as exc:
        without.put(req("a", "fresh", now, now + 60.0))
    assert exc.value.code == ErrorCode.OVERLOADED


def test_requests_a_full_queue_shed_are_answered_at_shutdown_too():
    """As DEADLINE_EXCEEDED, which they are: the engine's stop answered them UNAVAILABLE ("retry") with the queued,
    so a robot could send again a request already past its deadline."""
    q = ModelQueues(["a"], max_queue=1)
    now = time.monotonic()
    q.put(req("a", "old", now - 1.0, now - 0.5))
    q.put(req("a", "fresh", now, now + 60.0))
    queued, shed = q.close()
    assert [r.id for r in queued] == ["fresh"] and [r.id for r in shed] == ["old"]
    answers: list = []
    engine = MonolithicEngine({"toy": ServedModel("toy", build_model("toy", seed=1), 0.5)},
                              EngineConfig(max_batch=2, max_queue=1), torch.device("cpu"), answers.extend)
    engine.submit(req("toy", "old", now - 1.0, now - 0.5))
    engine.submit(req("toy", "fresh", now, now + 60.0))
    engine.finish()
    assert sorted((r.request.id, r.error[0]) for r in answers) == [("fresh", ErrorCode.UNAVAILABLE),
                                                                  ("old", ErrorCode.DEADLINE_EXCEEDED)]


def test_a_new_run_of_the_engine_starts_shed_late_afresh():
    """The service-time window outlived finish()/run(): an engine reused for the next epoch or capacity point shed
    feasible requests by how slow the overloaded point before had been."""
    q = ModelQueues(["a"], shed_late=True)
    now = time.monotonic()
    for _ in range(8):
        q.note_service("a", 0.18, now=now)
    assert q.service_estimate("a", now=now) == pytest.approx(0.18)
    q.close()
    q.reopen()
    assert q.service_estimate("a", now=now) == 0.0
    q.put(req("a", "r", now, now + 0.1))
    assert [r.id for r in q.take(1, now=now)[1]] == ["r"]


def test_a_sink_that_fails_on_the_shed_answers_does_not_lose_the_batch_taken_with_them():
    """The monolithic engine handed the shed requests to the sink unguarded: a fault there raised out of its step,
    and the batch taken in the same take() was never run nor answered."""
    model = build_model("toy", "tiny")
    answered: list[str] = []

    def sink(results):
        if any(r.error is not None for r in results):
            raise RuntimeError("the I/O layer failed")
        answered.extend(r.request.id for r in results)

    eng = MonolithicEngine({"toy": ServedModel("toy", model, 60.0)}, EngineConfig(max_batch=2), torch.device("cpu"),
                           sink)
    images, state, tokens = model.example_inputs(1)
    now = time.monotonic()
    for rid, deadline in (("late", now - 1.0), ("fine", now + 60.0)):
        eng.queues.put(Request(id=rid, robot="r", model="toy", images=images[0].numpy(), state=state[0].numpy(),
                               tokens=tokens[0].numpy(), arrival=now - 2.0, deadline=deadline,
                               noise=model.noise(1)[0].numpy()))
    assert eng.step()
    assert answered == ["fine"]


def test_peek_leaves_the_service_estimate_as_it_was():
    """peek read the estimate through a call that dropped a stale window, so whether a prestage happened to peek
    between two replies changed what shed_late would shed (0.05 s without a peek, 0.01 with one)."""
    estimates = []
    for peek in (False, True):
        q = ModelQueues(["a"], policy="esf", shed_late=True)
        q.note_service("a", 0.05, now=1.0)
        q.put(req("a", "a1", 2.4, 9.0))
        if peek:
            assert q.peek(2, now=2.5)[0] == "a"
        q.note_service("a", 0.01, now=2.6)  # after a gap longer than STALE_S: a fresh window either way
        estimates.append(q.service_estimate("a", now=2.6))
    assert estimates == [pytest.approx(0.01), pytest.approx(0.01)]


def _light_model_beside_an_overloading_one(policy: str, shed_late: bool) -> dict:
    """Virtual time, the real queues: model a (50 ms deadline) arrives at 2.5x what the stand-in GPU serves (a batch
    of up to 2 takes 20 ms, one taken every 10 ms), model b (1 s deadline) at 10 requests/s, for 20 s.
    Returns b's outcomes."""
    q = ModelQueues(["a", "b"], max_queue=256, policy=policy, shed_expired=True, shed_late=shed_late)
    arrivals = sorted([(k * 0.002, "a", 0.05) for k in range(10_000)] + [(k * 0.1 + 0.0007, "b", 1.0)
                                                                         for k in range(200)])
    b: dict = {"met": 0, "late": 0, "shed": 0, "refused": 0}
    running: list = []
    now, i = 0.0, 0
    while now < 22.0:
        while i < len(arrivals) and arrivals[i][0] <= now:
            t, model, slo = arrivals[i]
            i += 1
            try:
                q.put(req(model, f"{model}{i}", t, t + slo))
            except ProtocolError:
                b["refused"] += model == "b"
        for done in [x for x in running if x[0] <= now]:
            running.remove(done)
            finished, model, batch = done
            if model == "b":
                b["met"] += sum(finished <= r.deadline for r in batch)
                b["late"] += sum(finished > r.deadline for r in batch)
            q.note_service(model, 0.02, now=finished)
        model, batch, shed = q.take(2, now=now)
        b["shed"] += sum(r.model == "b" for r in shed)
        if batch:
            running.append((now + 0.02, model, batch))
        now += 0.01
    return b


def test_a_light_model_beside_an_overloading_one_is_starved_by_esf_and_lqf_and_served_by_rr():
    """What docs/engine.md ("Starvation under overload") says: not delayed to its last milliseconds, starved."""
    assert _light_model_beside_an_overloading_one("rr", False)["met"] == 200
    for policy, shed_late in (("esf", False), ("esf", True), ("lqf", False)):
        b = _light_model_beside_an_overloading_one(policy, shed_late)
        assert sum(b.values()) == 200 and b["met"] < 100, (policy, shed_late, b)
