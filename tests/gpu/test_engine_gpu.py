"""The lockstep engine on a real GPU: restriction, overlap, correctness (`pytest -m gpu`)."""

import faulthandler
import statistics
import threading
import time

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.gpu

if not torch.cuda.is_available():  # collected on CPU hosts only to be deselected/skipped
    pytest.skip("needs a CUDA GPU", allow_module_level=True)

import triton  # noqa: E402
import triton.language as tl  # noqa: E402

import bench.models  # noqa: E402,F401  (registers heavytoy)
from services.executor.engine import ServedModel  # noqa: E402
from services.executor.lockstep import LockstepEngine  # noqa: E402
from services.executor.scheduler import Request, Result  # noqa: E402
from services.executor.sm import GreenStreams, StaticLevel, TableLevel, Unrestricted  # noqa: E402
from shared.config import EngineConfig  # noqa: E402
from shared.models import build_model  # noqa: E402
from tests.gpu.zoo import DEV, blas_settings, eager, matmul_ms, requests, worst_error_vs_eager  # noqa: E402


@pytest.fixture(autouse=True)
def watchdog():
    # A stream or graph mistake hangs instead of failing: dump stacks and exit rather than wait forever.
    faulthandler.dump_traceback_later(300, exit=True)
    yield
    faulthandler.cancel_dump_traceback_later()


def _time_graph(graph: torch.cuda.CUDAGraph, stream: torch.cuda.Stream, n: int = 10) -> float:
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    with torch.cuda.stream(stream):
        graph.replay()
        start.record(stream)
        for _ in range(n):
            graph.replay()
        end.record(stream)
    end.synchronize()
    return start.elapsed_time(end) / n


def test_graph_captured_on_green_stream_runs_restricted():
    green = GreenStreams(DEV, [16])
    plain = torch.cuda.Stream(DEV)
    a = torch.randn(8192, 8192, device=DEV, dtype=torch.bfloat16)
    graphs = {}
    for name, stream in (("full", plain), ("16", green.stream(16))):
        stream.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(stream):
            a @ a
        stream.synchronize()
        g = torch.cuda.CUDAGraph()
        with torch.cuda.graph(g, stream=stream):
            a @ a
        graphs[name] = g
    # Both replayed on the same plain stream: the restriction travels with the graph.
    full, restricted = _time_graph(graphs["full"], plain), _time_graph(graphs["16"], plain)
    print(f"8192^3 bf16 matmul graph: unrestricted {full:.2f} ms, captured on 16 SMs {restricted:.2f} ms")
    assert restricted > 3.0 * full


@triton.jit
def _sm_ids(out_ptr):
    sm = tl.inline_asm_elementwise("mov.u32 $0, %smid;", "=r", [], dtype=tl.int32, is_pure=False, pack=1)
    tl.store(out_ptr + tl.program_id(0), sm)


def test_level_and_its_complement_share_no_sm():
    """Work on a level's green stream and on ``complement(level)`` runs on disjoint SM sets
    that together cover the GPU (read from each program's %smid)."""
    total = torch.cuda.get_device_properties(DEV).multi_processor_count
    green = GreenStreams(DEV, [48, 96])
    for level in (48, 96):
        used = {}
        free, free_sms = green.complement(level)
        for name, stream in (("level", green.stream(level)), ("complement", free)):
            out = torch.full((total * 64,), -1, dtype=torch.int32, device=DEV)
            stream.wait_stream(torch.cuda.current_stream(DEV))
            with torch.cuda.stream(stream):
                _sm_ids[(out.numel(),)](out)
            stream.synchronize()
            used[name] = set(out.tolist())
        print(f"level {level}: {len(used['level'])} SMs used, complement {len(used['complement'])} of {free_sms}")
        assert -1 not in used["level"] | used["complement"]
        assert len(used["level"]) == level and len(used["complement"]) == free_sms == total - level
        assert not used["level"] & used["complement"]


def _engine(models: dict, cfg: EngineConfig, policy=None) -> tuple[LockstepEngine, list[Result]]:
    results: list[Result] = []
    lock = threading.Lock()

    def sink(rs):
        with lock:
            results.extend(rs)

    eng = LockstepEngine({n: ServedModel(n, m, 1.0) for n, m in models.items()}, cfg, DEV, sink, sm_policy=policy)
    eng.prepare()
    return eng, results


def _lockstep_ms(eng: LockstepEngine, vlm, act, level=None, n: int = 10) -> float:
    runner = eng.runner
    times = []
    for i in range(n + 2):
        runner.begin(i)
        if act is not None:
            runner.launch_handoff(act[0], act[1])
            runner.launch_action(act[0], act[1], 0)
        if vlm is not None:
            runner.launch_vlm(vlm[0], vlm[1], level, after_handoff=False)
        runner.end_launch()
        runner.wait()
        if i >= 2:
            times.append(runner.measure(i, False).duration_ms)
    return statistics.median(times)


def test_concurrent_stages_overlap():
    model = build_model("heavytoy", "full", device=DEV)
    eng, _ = _engine({"h": model}, EngineConfig(kind="robion", max_batch=2), StaticLevel(96))
    st = eng.stages["h"]
    st.capture_vlm(2, {None, 96})
    vlm_solo = _lockstep_ms(eng, (st, 2), None)
    act_solo = _lockstep_ms(eng, None, (st, 2))
    both = _lockstep_ms(eng, (st, 2), (st, 2))
    both96 = _lockstep_ms(eng, (st, 2), (st, 2), level=96)
    print(f"batch 2: VLM {vlm_solo:.2f} ms, action {act_solo:.2f} ms, serial {vlm_solo + act_solo:.2f} ms, "
          f"lockstep unrestricted {both:.2f} ms, VLM on 96 SMs {both96:.2f} ms")
    assert min(both, both96) < 0.95 * (vlm_solo + act_solo)


def _serve(eng: LockstepEngine, reqs: list[Request], results: list[Result], queued: bool = False) -> None:
    """Runs the engine until every request is answered. Arrivals are spread over locksteps, so
    batch sizes vary, or with ``queued`` all submitted before it starts (saturating)."""
    if queued:
        for r in reqs:
            eng.submit(r)
    stop = threading.Event()
    t = threading.Thread(target=eng.run, args=(stop,))
    t.start()
    if not queued:
        for i, r in enumerate(reqs):
            eng.submit(r)
            if i % 5 == 4:
                time.sleep(0.003)
    deadline = time.monotonic() + 120
    while len(results) < len(reqs) and time.monotonic() < deadline:
        time.sleep(0.01)
    stop.set()
    t.join(60)
    assert not t.is_alive()


def _check(models: dict, results: list[Result], n: int) -> float:
    worst = worst_error_vs_eager(models, results, n)
    assert worst < 3e-2, worst  # bf16 through 10 Euler steps, batched vs single
    # The comparison must be able to fail: another request's observation (same noise) differs by more.
    a, b = results[0].request, next(r.request for r in results if r.request.model == results[0].request.model
                                    and r.request.id != results[0].request.id)
    swapped = Request(**{**a.__dict__, "images": b.images, "state": b.state, "tokens": b.tokens})
    ref, other = eager(models[a.model], a), eager(models[a.model], swapped)
    sensitivity = float(np.linalg.norm(ref - other) / np.linalg.norm(ref))
    print(f"worst relative error {worst:.2e}; another observation moves the actions by {sensitivity:.2e}")
    assert sensitivity > 10 * max(worst, 1e-4)
    return worst


@pytest.mark.parametrize("policy", ["table", "none", "table-eager"])
def test_lockstep_results_equal_eager_single_and_co_located(policy):
    """``table-eager``: no CUDA graphs (``engine.graphs: false``), so each restricted VLM runs eagerly on its
    level's green stream, and its action stage on the action stream beside it."""
    h1 = build_model("heavytoy", "full", seed=1, device=DEV)
    h2 = build_model("heavytoy", "full", seed=2, device=DEV)  # a fine-tuned variant: same table entries
    toy = build_model("toy", "full", seed=3, device=DEV)
    models = {"h1": h1, "h2": h2, "toy": toy}
    if policy.startswith("table"):  # a hand-made table: restricted levels on some pairs, without minutes of profiling
        sm = TableLevel({("heavytoy:full", 2, "heavytoy:full", 2): 96, ("heavytoy:full", 1, "heavytoy:full", 2): 64,
                         ("heavytoy:full", 2, "toy:full", 1): 112, ("toy:full", 1, "heavytoy:full", 1): 32})
    else:
        sm = Unrestricted()
    eng, results = _engine(models, EngineConfig(kind="robion", max_batch=2, graphs=policy != "table-eager"), sm)
    assert eng.runner.eager_vlm == (policy == "table-eager")
    reqs = requests(h1, "h1", 12, 0) + requests(h2, "h2", 12, 1) + requests(toy, "toy", 12, 2)
    order = np.random.default_rng(3).permutation(len(reqs))
    _serve(eng, [reqs[i] for i in order], results)
    worst = _check(models, results, len(reqs))
    summary = eng.telemetry.summary()
    print(f"policy {policy}: worst relative error {worst:.2e}; telemetry {summary}")
    # Eager launching is CPU-bound (each stage's hundreds of kernels are issued from Python, about 20 ms here), so
    # a stage has mostly run by the time the other's launch begins: both share locksteps, but seldom run at once.
    assert summary["co_running"] > 0 if policy == "table-eager" else summary["overlapping"] > 0
    if policy.startswith("table"):
        assert set(summary["sm_levels"]) - {"None"}, "some lockstep should have run restricted"


def test_restricted_vlm_capture_plans_gemms_for_its_level_and_restores_settings():
    """A VLM graph captured at a level is planned through cuBLASLt for that many SMs; an
    unrestricted one is not; torch's process-wide settings come back after each capture,
    also when the capture fails."""
    h = build_model("heavytoy", "full", seed=7, device=DEV)
    eng, _ = _engine({"h": h}, EngineConfig(kind="robion", max_batch=2), StaticLevel(64))
    st = eng.stages["h"]
    before = blas_settings()
    seen: list[tuple] = []
    body = st._vlm_body

    def spying(b):
        seen.append(blas_settings())
        return body(b)

    st._vlm_body = spying
    st.drop_vlm({})
    st.capture_vlm(1, {64, None})  # restricted levels are captured first
    total = torch.cuda.get_device_properties(DEV).multi_processor_count
    runs = len(seen) // 2
    assert set(seen[:runs]) == {(torch._C._BlasBackend.Cublaslt, total - 64)}
    assert set(seen[runs:]) == {before}
    assert blas_settings() == before

    def failing(b):
        raise RuntimeError("capture failed")

    st._vlm_body = failing
    with pytest.raises(RuntimeError, match="capture failed"):
        st.capture_vlm(2, {64})
    assert blas_settings() == before


def test_table_action_plan_is_captured_and_serves_equal_to_eager(tmp_path):
    """An SM table that planned an action graph for fewer SMs makes the engine capture that
    graph through cuBLASLt planned for them (and the other batch's as torch calls it)."""
    from services.executor.profiler import GEMM_PLAN, ProfileEntry, SMTable

    h = build_model("heavytoy", "full", seed=9, device=DEV)
    arch = "heavytoy:full"
    table = SMTable(torch.cuda.get_device_name(DEV), torch.cuda.get_device_properties(DEV).multi_processor_count,
                    torch.__version__, 2, [arch], gemm_plan=GEMM_PLAN,
                    action_plans={f"{arch}|2": 76, f"{arch}|1": None}, action_confine={f"{arch}|1": 64})
    table.entries = [ProfileEntry(arch, vb, arch, ab, 56, 1.0, 1.0, {"56": 1.0, "none": 1.0})
                     for vb in (1, 2) for ab in (1, 2)]
    table.save(tmp_path / "table.json")
    eng, results = _engine({"h": h}, EngineConfig(kind="robion", max_batch=2, sm_table=str(tmp_path / "table.json")))
    st = eng.stages["h"]
    assert st.action_plans == {1: None, 2: 76} and st.action_confine == {1: 64, 2: None}
    before = blas_settings()
    seen: dict[int, set] = {}
    body = st._action_body

    def spying(b):
        seen.setdefault(b, set()).add((blas_settings(), torch.cuda.current_stream(DEV).cuda_stream))
        return body(b)

    st._action_body = spying
    st.action_graphs.clear()
    st.capture_action()
    total = torch.cuda.get_device_properties(DEV).multi_processor_count
    free, free_sms = eng.green.complement(64)
    assert free_sms == total - 64
    # Batch 2 planned for 76 SMs on the action stream; batch 1 confined to the SMs a 64-SM VLM
    # leaves free, planned for them.
    assert seen == {2: {((torch._C._BlasBackend.Cublaslt, total - 76), eng.runner.action_stream.cuda_stream)},
                    1: {((torch._C._BlasBackend.Cublaslt, 64), free.cuda_stream)}}
    assert blas_settings() == before
    st._action_body = body
    reqs = requests(h, "h", 16, 8)
    _serve(eng, reqs, results)
    _check({"h": h}, results, len(reqs))


def test_profiling_tries_planned_action_graphs_and_keeps_stages_consistent(tmp_path, monkeypatch):
    """Profiling a table tries each action graph planned for the SMs its same-model lockstep
    leaves free; every stage's action graph is then the one the table serves with, and
    serving stays equal to eager. The gain threshold is lifted so that profiling keeps its
    best candidates whatever their timing: the engine must capture them again after profiling."""
    from services.executor import profiler

    monkeypatch.setattr(profiler, "PLAN_MIN_GAIN", -10.0)  # keep a candidate up to 11x slower
    h1 = build_model("heavytoy", "full", seed=11, device=DEV)
    h2 = build_model("heavytoy", "full", seed=12, device=DEV)  # same architecture: one profile
    cfg = EngineConfig(kind="robion", max_batch=2, sm_table=str(tmp_path / "profiled.json"), profile_repeats=3)
    eng, results = _engine({"h1": h1, "h2": h2}, cfg)
    table = eng.table
    arch = "heavytoy:full"
    assert set(table.action_plans) == {f"{arch}|1", f"{arch}|2"}  # a fresh table tries every action graph
    kept = [b for b in (1, 2) if table.action_plans[f"{arch}|{b}"] or table.action_confine.get(f"{arch}|{b}")]
    assert kept, "profiling kept no planned or confined action graph"
    entries = {e.combo: e for e in table.entries}
    for b in (1, 2):
        for name in ("h1", "h2"):
            assert eng.stages[name].action_plans.get(b) == table.action_plans[f"{arch}|{b}"]
            assert eng.stages[name].action_confine.get(b) == table.action_confine.get(f"{arch}|{b}")
    # The saved table keeps the plain graphs' timings and each candidate's in every combination with it.
    saved = profiler.SMTable.load(tmp_path / "profiled.json")
    assert set(saved.plan_entries) == {f"{arch}|{b}" for b in kept}
    for b in kept:
        assert {e.combo for e in saved.plan_entries[f"{arch}|{b}"]} == {(arch, vb, arch, b) for vb in (1, 2)}
    print(f"action plans {table.action_plans}, confined {table.action_confine}; same-model best levels "
          f"{[(b, entries[(arch, b, arch, b)].best_sms) for b in (1, 2)]}")
    reqs = requests(h1, "h1", 10, 9) + requests(h2, "h2", 10, 10)
    _serve(eng, reqs, results)
    _check({"h1": h1, "h2": h2}, results, len(reqs))


def test_each_model_alone_equals_eager():
    h = build_model("heavytoy", "full", seed=5, device=DEV)
    eng, results = _engine({"h": h}, EngineConfig(kind="robion", max_batch=2), StaticLevel(88))
    reqs = requests(h, "h", 16, 4)
    _serve(eng, reqs, results)
    _check({"h": h}, results, len(reqs))
    assert eng.telemetry.summary()["overlapping"] > 0


def test_launch_ahead_under_load_is_correct_and_hides_the_launch():
    """A full queue keeps locksteps back to back: almost every lockstep is issued ahead (behind
    the previous one's end events), replies still equal eager, and the device idles between
    locksteps for less than the host takes to issue one."""
    h = build_model("heavytoy", "full", seed=6, device=DEV)
    models = {"h": h}
    eng, results = _engine(models, EngineConfig(kind="robion", max_batch=2),
                           TableLevel({("heavytoy:full", 2, "heavytoy:full", 2): 96}))
    assert eng._launch_ahead
    reqs = requests(h, "h", 60, 8)
    _serve(eng, reqs, results, queued=True)
    _check(models, results, len(reqs))
    s = eng.telemetry.summary()
    print(f"launch-ahead: {s['ahead']}/{s['back_to_back']} issued ahead; host gap {s['cpu_gap_us']}; "
          f"GPU idle {s['gpu_gap_us']}; launch {s['launch_us']}; admitted early {s['admit_early_us']}")
    assert s["ahead"] >= 0.5 * s["back_to_back"] > 0
    assert s["gpu_gap_us"]["median"] < s["launch_us"]["median"]


def test_disjoint_split_gives_two_partitions():
    from services.executor.sm import split_disjoint

    part = split_disjoint(DEV, 64)
    assert part.vlm_sms == 64 and part.action_sms == torch.cuda.get_device_properties(DEV).multi_processor_count - 64
    times = matmul_ms({"full": torch.cuda.Stream(DEV), "vlm": part.vlm_stream, "action": part.action_stream})
    print(f"disjoint split: all SMs {times['full']:.2f} ms, {part.vlm_sms} SMs {times['vlm']:.2f} ms, "
          f"{part.action_sms} SMs {times['action']:.2f} ms")
    # About half the SMs each: both clearly slower than the whole device.
    assert times["vlm"] > 1.5 * times["full"] and times["action"] > 1.4 * times["full"]
