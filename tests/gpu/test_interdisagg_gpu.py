"""Inter-GPU stage disaggregation on real GPUs (`pytest -m gpu`, needs at least 2): the VLM stage on
cuda:0, the action stage on the other GPUs, replies equal eager on cuda:0."""

import gc

import pytest
import torch

pytestmark = pytest.mark.gpu
if not torch.cuda.is_available() or torch.cuda.device_count() < 2:
    pytest.skip("needs at least 2 CUDA GPUs", allow_module_level=True)

from shared.models import build_model  # noqa: E402
from tests.gpu.test_baselines_gpu import serve  # noqa: E402
from tests.gpu.zoo import DEV, requests, worst_error_vs_eager  # noqa: E402
from tests.gpu.test_baselines_gpu import watchdog  # noqa: E402,F401  (an autouse fixture)


@pytest.mark.parametrize("graphs", [True, False])
def test_pi0_across_devices_equals_eager(graphs):
    n = torch.cuda.device_count()
    model = build_model("pi0", "full", seed=0, device=DEV)
    reqs = requests(model, "pi0", 12, 0)
    # Handoffs cross devices (peer-to-peer where the GPUs allow it); batch sizes 1 and 2.
    eng, results, prep = serve("interdisagg", model, reqs, graphs=graphs, vlm_devices="0",
                               action_devices="+".join(str(i) for i in range(1, n)))
    worst = worst_error_vs_eager({"pi0": model}, results, len(reqs))
    print(f"\ninterdisagg graphs={graphs}: prepare {prep:.1f} s, worst relative error vs eager {worst:.2e}; "
          f"peer access {eng.peer_access}; telemetry {eng.telemetry.summary()}")
    assert worst < 3e-2, worst
    assert {r.action_worker for r in eng.telemetry.records()} <= set(range(n - 1))
    del eng
    gc.collect()
    torch.cuda.empty_cache()
