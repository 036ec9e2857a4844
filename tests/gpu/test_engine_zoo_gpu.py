"""The robion engine serving the four zoo models on the GPU, alone and co-located (`pytest -m gpu`).

Every reply must equal running the model eagerly on the same observation and noise (bf16
tolerance) and the lockstep telemetry must show the two stages overlapping. The SM table is
the profiled one (ROBION_SM_TABLE, default bench/results/sm_table_h100_zoo.json); a missing
table is profiled first, which takes minutes.
"""

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

from services.executor.engine import ServedModel  # noqa: E402
from services.executor.lockstep import LockstepEngine  # noqa: E402
from services.executor.scheduler import Result  # noqa: E402
from shared.config import EngineConfig  # noqa: E402
from shared.models import build_model  # noqa: E402
from tests.gpu.zoo import DEV, requests, worst_error_vs_eager  # noqa: E402
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
TABLE = os.environ.get("ROBION_SM_TABLE", os.path.join(ROOT, "bench", "results", "sm_table_h100_zoo.json"))
SPECS = {"pi0": ("pi0", 0), "pi0-ft": ("pi0", 7), "smolvla": ("smolvla", 0), "groot": ("groot_n15", 0), "xr0": ("xr0", 0)}


@pytest.fixture(autouse=True)
def watchdog():
    faulthandler.dump_traceback_later(540, exit=True)
    yield
    faulthandler.cancel_dump_traceback_later()


@pytest.fixture(scope="module")
def zoo():
    return {name: build_model(arch, "full", seed=seed, device=DEV) for name, (arch, seed) in SPECS.items()}


@pytest.mark.parametrize("names", [["pi0"], ["smolvla"], ["groot"], ["xr0"], ["pi0", "xr0"],
                                   ["pi0", "pi0-ft", "smolvla", "groot", "xr0"]],
                         ids=lambda n: "+".join(n))
def test_zoo_served_by_lockstep_engine_equals_eager(zoo, names):
    models = {n: zoo[n] for n in names}
    results: list[Result] = []
    lock = threading.Lock()

    def sink(rs):
        with lock:
            results.extend(rs)

    cfg = EngineConfig(kind="robion", max_batch=2, sm_table=TABLE)
    eng = LockstepEngine({n: ServedModel(n, m, 1.0) for n, m in models.items()}, cfg, DEV, sink)
    eng.prepare()
    reqs = [r for k, n in enumerate(names) for r in requests(models[n], n, 10, k)]
    order = np.random.default_rng(len(names)).permutation(len(reqs))
    stop = threading.Event()
    t = threading.Thread(target=eng.run, args=(stop,))
    t.start()
    for i, j in enumerate(order):
        eng.submit(reqs[j])
        if i % 3 == 2:
            time.sleep(0.004)  # arrivals spread over locksteps: batch sizes 1 and 2 both occur
    end = time.monotonic() + 120
    while len(results) < len(reqs) and time.monotonic() < end:
        time.sleep(0.01)
    stop.set()
    t.join(60)
    worst = worst_error_vs_eager(models, results, len(reqs))
    summary = eng.telemetry.summary()
    gaps = [r.cpu_gap_us for r in eng.telemetry.records() if r.cpu_gap_us is not None]
    print(f"\n{'+'.join(names)}: {len(reqs)} replies, worst relative error vs eager {worst:.2e}; "
          f"telemetry {summary}; cpu gap median {np.median(gaps) if gaps else float('nan'):.0f} us")
    assert worst < 3e-2, worst
    assert summary["overlapping"] > 0
    del eng
    gc.collect()
    torch.cuda.empty_cache()
