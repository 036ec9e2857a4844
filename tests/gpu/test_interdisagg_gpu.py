"""Inter-GPU stage disaggregation on real GPUs (`pytest -m gpu`, needs at least 2): the VLM stage on
cuda:0, the action stage on the other GPUs, replies equal eager on cuda:0."""

import gc

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.gpu
if not torch.cuda.is_available() or torch.cuda.device_count() < 2:
    pytest.skip("needs at least 2 CUDA GPUs", allow_module_level=True)

from shared.models import build_model  # noqa: E402
from tests.gpu.test_baselines_gpu import DEV, eager, requests, serve  # noqa: E402
from tests.gpu.test_baselines_gpu import watchdog  # noqa: E402,F401  (an autouse fixture)


@pytest.mark.parametrize("graphs", [True, False])
def test_pi0_across_devices_equals_eager(graphs):
    n = torch.cuda.device_count()
    model = build_model("pi0", "full", seed=0, device=DEV)
    reqs = requests(model, "pi0", 12, 0)
    # Handoffs cross devices (peer-to-peer where the GPUs allow it); batch sizes 1 and 2.
    eng, results, prep = serve("interdisagg", model, reqs, graphs=graphs, vlm_devices="0",
                               action_devices="+".join(str(i) for i in range(1, n)))
    assert len(results) == len(reqs) and len({r.request.id for r in results}) == len(reqs)
    worst = 0.0
    for res in results:
        assert res.error is None, res.error
        ref = eager(model, res.request)
        worst = max(worst, float(np.linalg.norm(res.actions - ref) / np.linalg.norm(ref)))
    print(f"\ninterdisagg graphs={graphs}: prepare {prep:.1f} s, worst relative error vs eager {worst:.2e}; "
          f"peer access {eng.peer_access}; telemetry {eng.telemetry.summary()}")
    assert worst < 3e-2, worst
    assert {r.action_worker for r in eng.telemetry.records()} <= set(range(n - 1))
    del eng
    gc.collect()
    torch.cuda.empty_cache()
