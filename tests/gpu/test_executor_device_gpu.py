"""The executor process on a GPU host (`pytest -m gpu`): a GPU index past the host's is refused by name."""

import pytest
import torch

pytestmark = pytest.mark.gpu
if not torch.cuda.is_available():
    pytest.skip("needs a CUDA GPU", allow_module_level=True)

from tests.helpers import cluster_config, executor_exit  # noqa: E402


def test_a_gpu_index_past_the_hosts_stops_the_executor_with_the_device_named(tmp_path):
    """cuda:N with N = the host's GPU count passes the config's check; torch failed with a traceback."""
    count = torch.cuda.device_count()
    path, _ = cluster_config(tmp_path)
    res = executor_exit(path, "--device", f"cuda:{count}", timeout_s=300)
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    assert f"device cuda:{count}: this host shows {count} CUDA GPU(s), cuda:0 to cuda:{count - 1}" in res.stderr, \
        res.stderr[-2000:]
    assert "Traceback" not in res.stderr, res.stderr[-2000:]


@pytest.mark.parametrize("replica", [False, True], ids=["configured", "replica"])
def test_models_beyond_the_gpus_free_memory_stop_the_executor_before_loading(tmp_path, replica):
    """One full-size XR0 model (about 11 GiB by the estimate) more than the GPU's free memory holds: the executor exits
    2 naming its models before it loads one. A replica scaled out with --models (as docker-compose does) used to skip
    the check and run out of memory part-way through loading."""
    from shared.placement import model_bytes

    free, _ = torch.cuda.mem_get_info(0)
    count = free // model_bytes("xr0", "full", 2) + 1  # 8 on an 80 GB H100, 13 on an H200
    models = [{"name": f"xr0-{i}", "arch": "xr0", "size": "full", "seed": i, "slo_ms": 117} for i in range(count)]
    names = [m["name"] for m in models]
    path, _ = cluster_config(tmp_path, models=models, executors=[{"name": "g0", "device": "cuda:0", "models": names}])
    # A replica's device is its --device (the config's default, cpu, otherwise).
    args = ("--name", "rep0", "--models", ",".join(names), "--device", "cuda:0") if replica else ("--name", "g0")
    res = executor_exit(path, *args, timeout_s=300)
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    where = "--models" if replica else "executors[0].models"
    assert f"{where}: the models placed on {'rep0' if replica else 'g0'} need about" in res.stderr, res.stderr[-2000:]
    assert "but it has" in res.stderr and "Traceback" not in res.stderr, res.stderr[-2000:]
