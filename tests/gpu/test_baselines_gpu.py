"""The comparison engines on the GPU (`pytest -m gpu`): replies equal eager on a zoo model,
the disjoint partition restricts both streams, procdisagg merges arrivals into a running batch."""

import faulthandler
import gc
import os
import threading
import time

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.gpu
if not torch.cuda.is_available():
    pytest.skip("needs a CUDA GPU", allow_module_level=True)

from services.executor.engine import ServedModel, make_engine  # noqa: E402
from services.executor.scheduler import Request, Result  # noqa: E402
from shared.config import EngineConfig  # noqa: E402
from shared.models import build_model  # noqa: E402
from tests.gpu.zoo import DEV, blas_settings, matmul_ms, requests, worst_error_vs_eager  # noqa: E402
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
TABLE = os.environ.get("ROBION_SM_TABLE", os.path.join(ROOT, "bench", "results", "sm_table_h100_zoo.json"))
KINDS = {"monolithic": {}, "robion": {"sm_table": TABLE}, "disagg": {}, "static": {},
         "disjoint": {"disjoint_sms": 64}, "procdisagg": {}}


@pytest.fixture(autouse=True)
def watchdog():
    faulthandler.dump_traceback_later(300, exit=True)
    yield
    faulthandler.cancel_dump_traceback_later()


@pytest.fixture(scope="module")
def pi0():
    return build_model("pi0", "full", seed=0, device=DEV)


def serve(kind: str, model, reqs: list[Request], gap_every: int = 3, **cfg):
    results: list[Result] = []
    lock = threading.Lock()

    def sink(rs):
        with lock:
            results.extend(rs)

    eng = make_engine({"pi0": ServedModel("pi0", model, 1.0)}, EngineConfig(kind=kind, max_batch=2, **cfg), DEV, sink)
    t0 = time.perf_counter()
    eng.prepare()
    prep = time.perf_counter() - t0
    stop = threading.Event()
    t = threading.Thread(target=eng.run, args=(stop,))
    t.start()
    for i, r in enumerate(reqs):
        eng.submit(r)
        if i % gap_every == gap_every - 1:
            time.sleep(0.006)  # arrivals spread out: batch sizes 1 and 2, merges into running batches
    end = time.monotonic() + 120
    while len(results) < len(reqs) and time.monotonic() < end:
        time.sleep(0.01)
    stop.set()
    t.join(60)
    return eng, results, prep


@pytest.mark.parametrize("kind", list(KINDS))
def test_kind_serves_pi0_equal_to_eager(pi0, kind):
    reqs = requests(pi0, "pi0", 12, 0)
    eng, results, prep = serve(kind, pi0, reqs, **KINDS[kind])
    worst = worst_error_vs_eager({"pi0": pi0}, results, len(reqs))
    summary = eng.telemetry.summary()
    print(f"\n{kind}: prepare {prep:.1f} s, worst relative error vs eager {worst:.2e}; telemetry {summary}")
    assert worst < 3e-2, worst
    if kind == "procdisagg":
        eng.close()
    del eng
    gc.collect()
    torch.cuda.empty_cache()


def test_disjoint_partition_restricts_both_streams(pi0):
    eng, results, _ = serve("disjoint", pi0, requests(pi0, "pi0", 4, 1), disjoint_sms=32)
    part = eng.partition
    total = torch.cuda.get_device_properties(DEV).multi_processor_count
    assert (part.vlm_sms, part.action_sms) == (32, total - 32)
    assert eng.runner.vlm_stream is part.vlm_stream and eng.runner.action_stream is part.action_stream
    st = eng.stages["pi0"]
    assert st.capture_stream is part.vlm_stream and st.action_stream is part.action_stream  # graphs captured there
    assert st.stream_sms == (32, total - 32)
    assert all(r.error is None for r in results)
    # Captured again with a spy: each stage's GEMMs are planned through cuBLASLt for its partition.
    seen: dict[str, set] = {"vlm": set(), "action": set()}
    vlm_body, action_body = st._vlm_body, st._action_body

    st._vlm_body = lambda b: (seen["vlm"].add(blas_settings()), vlm_body(b))[1]
    st._action_body = lambda b: (seen["action"].add(blas_settings()), action_body(b))[1]
    before = blas_settings()
    st.drop_vlm({})
    st.action_graphs.clear()
    st.capture_vlm(1, {None})
    st.capture_action()
    lt = torch._C._BlasBackend.Cublaslt
    assert seen == {"vlm": {(lt, total - 32)}, "action": {(lt, 32)}}, seen
    assert blas_settings() == before
    times = matmul_ms({"full": torch.cuda.Stream(DEV), "vlm": part.vlm_stream, "action": part.action_stream})
    vlm = [r.vlm_ms for r in eng.telemetry.records() if r.vlm_batch == 2]
    print(f"\ndisjoint 32/{total - 32}: matmul full {times['full']:.2f} ms, VLM partition {times['vlm']:.2f} ms, "
          f"action partition {times['action']:.2f} ms; VLM b2 graph at 32 SMs {np.median(vlm) if vlm else 0:.2f} ms")
    assert times["vlm"] > 3.0 * times["full"]  # 32 of 132 SMs
    assert times["action"] > 1.15 * times["full"]  # 100 of 132 SMs
    del eng
    gc.collect()
    torch.cuda.empty_cache()


def test_procdisagg_merges_arrivals_between_denoising_steps(pi0):
    reqs = requests(pi0, "pi0", 24, 2)
    eng, results, _ = serve("procdisagg", pi0, reqs, gap_every=1)
    assert len(results) == len(reqs) and all(r.error is None for r in results)
    recs = eng.telemetry.records()
    # A merge: a step whose running batch already held requests when new ones joined it.
    merges = [r for r in recs if r.admitted and r.batch > r.admitted]
    mixed = [r for r in recs if len(set(r.row_steps)) > 1]
    changes = sum(1 for a, b in zip(recs, recs[1:]) if a.batch != b.batch or a.admitted or b.admitted)
    print(f"\nprocdisagg: {len(recs)} steps, {len(merges)} merges, {len(mixed)} steps with rows at different steps, "
          f"{changes} composition changes; {eng.telemetry.summary()}")
    assert merges and mixed
    assert sum(r.admitted for r in recs) == len(reqs) == sum(r.finished for r in recs)
    eng.close()
