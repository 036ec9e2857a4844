"""A user's own two-stage VLA, served by a real cluster exactly as docs/models.md shows it.

The registry only knew the built-in architectures in the services' processes: a class registered in the
user's module was unknown to `robion up` (config error) and to `robion models`. A config now names the
module under ``imports`` (found beside the config file too), and ROBION_IMPORTS names it for tools run
without a config. The module here is the docs' example, read from docs/models.md, so the two cannot drift.
"""

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch
import pytest
import yaml

from shared.client import RobotClient
from shared.cluster import LocalCluster
from shared.config import ConfigError, load_config
from tests.helpers import ROOT, cluster_config


def docs_example() -> str:
    text = (ROOT / "docs" / "models.md").read_text()
    section = text.split("## Serving your own two-stage VLA", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def user_config(tmp_path: Path, module: str = "my_vla") -> Path:
    (tmp_path / f"{module}.py").write_text(docs_example())
    path, data = cluster_config(tmp_path, models=[{"name": "mine", "arch": "my_vla", "size": "tiny", "slo_ms": 500}],
                                executors=[{"name": "ex0", "device": "cpu", "models": ["mine"]}])
    data["imports"] = [module]
    path.write_text(yaml.safe_dump(data))
    return path


def test_a_users_architecture_is_served_end_to_end(tmp_path):
    path = user_config(tmp_path, "my_vla_served")
    cfg = load_config(path)
    with LocalCluster(cfg, path, log_level="WARNING"):
        client = RobotClient(cfg.router.bind.replace("*", "127.0.0.1"), robot_id="arm-1")
        try:
            info = client.metadata()["mine"]
            assert info.cameras == ["base"] and list(info.image_shape) == [96, 96, 3] and info.state_dim == 8
            done = client.infer("mine", {"base": np.zeros((96, 96, 3), np.uint8)}, np.zeros(8, np.float32), "wave")
            assert done.actions.shape == (16, 7) and np.isfinite(done.actions).all()
        finally:
            client.close()


def test_a_module_that_cannot_be_imported_is_a_config_error(tmp_path):
    path = user_config(tmp_path, "my_vla_bad")
    data = yaml.safe_load(path.read_text())
    data["imports"] = ["no_such_module_here"]
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"imports\[0\]: cannot import 'no_such_module_here'"):
        load_config(path)
    data["imports"] = ["not a module"]
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"imports\[0\]: expected a Python module name"):
        load_config(path)
    # A module that exits at import (one that parses sys.argv, or calls sys.exit): SystemExit passed through, and a
    # `ctl apply` naming it ended the running control plane.
    (tmp_path / "exits_at_import.py").write_text("import sys\nsys.exit('needs a GPU library')\n")
    data["imports"] = ["exits_at_import"]
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"imports\[0\]: cannot import 'exits_at_import' \(SystemExit: needs a GPU"):
        load_config(path)


def test_a_bad_robion_imports_entry_is_a_config_error_for_a_service(tmp_path):
    """$ROBION_IMPORTS is read with a config too; a module it names that cannot be imported crashed the service
    with a traceback instead of one line and exit 2."""
    path = user_config(tmp_path, "my_vla_env")
    env = {**os.environ, "ROBION_IMPORTS": "no_such_module_here", "PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}"}
    res = subprocess.run([sys.executable, "-m", "services.executor.main", "-c", str(path), "--name", "ex0"],
                         capture_output=True, text=True, cwd=ROOT, env=env, timeout=120)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr[-2000:]
    assert "ROBION_IMPORTS: cannot import 'no_such_module_here'" in res.stderr


def test_robion_models_lists_the_modules_named_in_robion_imports(tmp_path):
    """As docs/models.md runs it: the `robion` script in the module's folder. The script, unlike `python -m`,
    does not put the working directory on sys.path, and the module was not found."""
    (tmp_path / "my_vla_listed.py").write_text(docs_example())
    env = {**os.environ, "ROBION_IMPORTS": "my_vla_listed", "PYTHONPATH": str(ROOT)}
    res = subprocess.run([str(Path(sys.executable).with_name("robion")), "models", "--json"], capture_output=True,
                         text=True, cwd=tmp_path, env=env, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert '"my_vla"' in res.stdout and '"horizon": 16' in res.stdout, res.stdout


# One line of the docs' example changed: each variant breaks the interface in a way that used to be served.
BROKEN = {
    "wrong_action_dim": ("        return x.to(noise.dtype)", "        return x.to(noise.dtype)[..., :5]",
                         r"action_stage: expected actions of shape \[1, 16, 7\]"),
    "one_row_short": ("        return x.to(noise.dtype)", "        return x.to(noise.dtype)[:1]",
                      r"action_stage: expected actions of shape \[2, 16, 7\] \[batch, horizon, action_dim\] at batch "
                      r"2, got \[1, 16, 7\]"),
    "no_batch_dim": ("        return x.to(noise.dtype)", "        return x.to(noise.dtype)[0]",
                     r"expected actions of shape \[1, 16, 7\] .* got \[16, 7\]"),
    "integer_actions": ("        return x.to(noise.dtype)", "        return x.to(torch.int32)",
                        r"expected floating-point actions, got torch.int32"),
    "handoff_not_a_dict": ('        return {"ctx": self.encoder(', '        return {self.encoder(',
                           r"vlm_stage: expected a dict of named tensors, got set"),
    "four_channels": ("image_shape=(96, 96, 3)", "image_shape=(96, 96, 4)",
                      r"io.image_shape: expected \(H, W, 3\)"),
    "no_cameras": ('cameras=("base",)', "cameras=()", r"io.cameras: expected a tuple of one or more"),
}


@pytest.mark.parametrize("variant", sorted(BROKEN))
def test_a_model_that_breaks_the_interface_is_refused_before_it_is_served(variant):
    """Engines copy stage outputs into static buffers, where a wrong shape broadcast: robots were answered with
    actions of the wrong size, or (one row short) every robot of a batch with the first robot's actions."""
    from shared.models.base import InterfaceError, check_interface

    old, new, message = BROKEN[variant]
    source = docs_example()
    assert old in source
    model = example_model(source.replace(old, new))
    with pytest.raises(InterfaceError, match=message):
        check_interface(model)


def example_model(source: str):
    """The docs' example class built from ``source``, tiny, unregistered."""
    namespace: dict = {}
    exec(compile(source.replace('@register("my_vla")', "@(lambda c: c)"), "docs_example", "exec"), namespace)
    return namespace["MyVLA"](namespace["MyConfig"](width=32))


def test_the_docs_example_and_every_zoo_model_follow_the_interface():
    from shared.models import build_model
    from shared.models.base import check_interface

    check_interface(example_model(docs_example()), batches=(1, 2, 3))
    for arch in ("pi0", "smolvla", "groot_n15", "xr0", "toy"):
        check_interface(build_model(arch, "tiny", seed=0, device="cpu"))


def start_executor(path: Path, tmp_path: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}"}
    return subprocess.run([sys.executable, "-m", "services.executor.main", "-c", str(path), "--name", "ex0"],
                          capture_output=True, text=True, cwd=ROOT, env=env, timeout=120)


def test_an_executor_refuses_a_model_one_row_short_with_one_line_and_exit_2(tmp_path):
    old, new, _ = BROKEN["one_row_short"]
    path = user_config(tmp_path, "my_vla_short")
    (tmp_path / "my_vla_short.py").write_text(docs_example().replace(old, new))
    res = start_executor(path, tmp_path)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr[-2000:]
    assert "cannot load models: MyVLA.action_stage: expected actions of shape [2, 16, 7]" in res.stderr


def test_an_engine_that_cannot_start_exits_2_with_one_line(tmp_path):
    """It raised out of main with a traceback and exit 1, which asks a supervisor to start it again: a model that
    fails the same way each time looped. This one refuses batches above 2, which only the engine's warm-up at
    max_batch 4 reaches."""
    path = user_config(tmp_path, "my_vla_small_batches")
    source = docs_example().replace("    def vlm_stage(self, images, state, tokens):\n",
                                    "    def vlm_stage(self, images, state, tokens):\n"
                                    "        assert images.shape[0] <= 2, 'batches of 3 or more are not supported'\n")
    (tmp_path / "my_vla_small_batches.py").write_text(source)
    data = yaml.safe_load(path.read_text())
    data["engine"]["max_batch"] = 4
    path.write_text(yaml.safe_dump(data))
    res = start_executor(path, tmp_path)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr[-2000:]
    assert ("cannot start the monolithic engine for ['mine']: AssertionError: batches of 3 or more are not "
            "supported") in res.stderr, res.stderr[-2000:]


ONE_ROBOT_AT_A_TIME = ("    def vlm_stage(self, images, state, tokens):\n",
                       "    def vlm_stage(self, images, state, tokens):\n"
                       "        assert images.shape[0] == 1, 'one robot at a time'\n")


def test_a_model_that_raises_in_its_check_is_refused_with_one_line_and_exit_2(tmp_path):
    """What a model's stage raised inside the check (anything but the check's own error) went out of main as a
    traceback and exit 1, which asks a supervisor to start it again."""
    path = user_config(tmp_path, "my_vla_one_at_a_time")
    (tmp_path / "my_vla_one_at_a_time.py").write_text(docs_example().replace(*ONE_ROBOT_AT_A_TIME))
    res = start_executor(path, tmp_path)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr[-2000:]
    assert ("cannot load models: MyVLA.vlm_stage failed at batch 2: AssertionError: one robot at a time"
            in res.stderr), res.stderr[-2000:]


def test_a_model_served_one_robot_at_a_time_is_checked_at_batch_1_only_and_io_lists_are_fine():
    """Checked at batch 2 regardless, a model served at max_batch 1 that takes one robot at a time was refused; and
    lists where the docs show tuples (cameras, image_shape) were refused though they were served before."""
    from services.executor.hosting import ModelStore
    from shared.config import ModelConfig
    from shared.models import register
    from shared.models.base import InterfaceError

    source = (docs_example().replace(*ONE_ROBOT_AT_A_TIME)
              .replace('@register("my_vla")', '@register("my_vla_batch_one")')
              .replace('cameras=("base",)', 'cameras=["base"]').replace("image_shape=(96, 96, 3)",
                                                                         "image_shape=[96, 96, 3]"))
    namespace: dict = {"register": register}
    exec(compile(source, "my_vla_batch_one", "exec"), namespace)
    mc = ModelConfig(name="mine", arch="my_vla_batch_one", size="tiny", slo_ms=500)
    hosted = ModelStore(torch.device("cpu"), max_batch=1).load([mc])
    assert hosted.inputs["mine"].info.cameras == ["base"]
    with pytest.raises(InterfaceError, match="vlm_stage failed at batch 2"):
        ModelStore(torch.device("cpu"), max_batch=2).load([mc])


def test_a_device_fault_in_the_check_is_not_a_refusal_of_the_model():
    """Out of device memory (maybe held by a process that just crashed) is no fault of the model: refused as one
    (exit 2), the executor was never started again. And a handoff_spec that is no mapping is a refusal, not a
    traceback."""
    from shared.models.base import InterfaceError, check_interface

    model = example_model(docs_example().replace(*ONE_ROBOT_AT_A_TIME).replace(
        "        assert images.shape[0] == 1, 'one robot at a time'\n",
        "        raise torch.OutOfMemoryError('CUDA out of memory. Tried to allocate 2.00 GiB')\n"))
    with pytest.raises(torch.OutOfMemoryError):
        check_interface(model)
    model = example_model(docs_example())
    model.handoff_spec = lambda batch: [("ctx", ((batch, 32), torch.float32))]
    with pytest.raises(InterfaceError, match="handoff_spec: expected"):
        check_interface(model)
