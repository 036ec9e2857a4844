"""A whole cluster as processes, its executor on the GPU (`pytest -m gpu`): the robion engine starts (SM table
profiled, CUDA graphs captured on green contexts) on its own thread while the I/O thread answers, then a robot
is served over real sockets."""

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.gpu
if not torch.cuda.is_available():
    pytest.skip("needs a CUDA GPU", allow_module_level=True)

from shared.client import RobotClient  # noqa: E402
from shared.cluster import LocalCluster  # noqa: E402
from shared.config import dial_address, load_config  # noqa: E402
from tests.helpers import cluster_config  # noqa: E402


def test_a_cluster_with_a_gpu_executor_serves_a_robot(tmp_path):
    path, _ = cluster_config(
        tmp_path, engine={"kind": "robion", "max_batch": 2, "profile_repeats": 2, "sm_table": str(tmp_path / "sm.json")},
        executors=[{"name": "gpu0", "device": "cuda:0", "models": ["toy-a", "toy-b"]}])
    cfg = load_config(path)
    cluster = LocalCluster(cfg, path, log_level="WARNING")
    status = cluster.start(timeout_s=600)
    try:
        assert status["executors"]["gpu0"]["device"] == "cuda:0"
        client = RobotClient(dial_address(cfg.router.bind), robot_id="arm-0")
        try:
            for model in ("toy-a", "toy-b"):
                info = client.metadata()[model]
                rng = np.random.default_rng(0)
                images = {c: rng.integers(0, 256, info.image_shape, dtype=np.uint8) for c in info.cameras}
                done = client.infer(model, images, np.zeros(info.state_dim, np.float32), "pick up the block",
                                    timeout_s=30)
                assert done.actions.shape == (info.horizon, info.action_dim) and np.isfinite(done.actions).all()
        finally:
            client.close()
        assert (tmp_path / "sm.json").exists()  # the SM table was profiled at the engine's start
    finally:
        codes = cluster.stop()
    assert all(code == 0 for code in codes.values()), codes
