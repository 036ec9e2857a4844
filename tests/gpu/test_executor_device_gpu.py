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
