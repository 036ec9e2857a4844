"""`robion` and the service entry points on bad input: a message and an exit code, never a traceback."""

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.helpers import cluster_config

ROOT = Path(__file__).resolve().parent.parent


def run(*argv: str, timeout: float = 120, **env) -> subprocess.CompletedProcess:
    import os

    return subprocess.run([sys.executable, "-m", *argv], capture_output=True, text=True, cwd=ROOT, timeout=timeout,
                          env={**os.environ, **env})


@pytest.mark.parametrize("argv", [
    ("shared.cli", "--log-level", "verbose", "models"),
    ("services.router.main", "-c", "configs/demo.yaml", "--log-level", "verbose"),
    ("services.controlplane.main", "-c", "configs/demo.yaml", "--log-level", "verbose"),
    ("services.fleet.main", "-c", "configs/demo.yaml", "--log-level", "verbose"),
])
def test_an_unknown_log_level_is_a_usage_error(argv):
    res = run(*argv)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert "--log-level" in res.stderr and "verbose" in res.stderr, res.stderr


def test_a_bad_ROBION_LOG_LEVEL_is_a_usage_error():
    res = run("services.router.main", "-c", "configs/demo.yaml", ROBION_LOG_LEVEL="chatty")
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert "chatty" in res.stderr, res.stderr


def test_log_levels_are_case_insensitive():
    from shared.service import log_level

    assert log_level("debug") == "DEBUG" and log_level("Warning") == "WARNING" and log_level("warn") == "WARN"


def test_ctl_apply_of_a_file_that_is_not_text(tmp_path):
    path, _ = cluster_config(tmp_path)
    binary = tmp_path / "weights.bin"
    binary.write_bytes(b"\x80\xd0\xff" * 100)
    res = run("shared.cli", "ctl", "apply", str(binary), "-c", str(path))
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert "robion ctl apply: cannot read" in res.stderr and str(binary) in res.stderr, res.stderr


@pytest.mark.parametrize("cmd", ["up", "demo"])
def test_a_service_that_fails_at_start_up_is_reported_without_traceback(tmp_path, cmd):
    path, data = cluster_config(tmp_path)
    data["models"][0]["weights"] = str(tmp_path / "missing.safetensors")  # both executors exit 2 while loading
    path.write_text(yaml.safe_dump(data))
    res = run("shared.cli", cmd, "-c", str(path), "--timeout", "90")
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    assert f"robion {cmd}: executor[" in res.stderr and "exited with code 2 during start-up" in res.stderr, res.stderr
    assert "weights file not found" in res.stderr  # the executor's own log line says why


def test_a_cluster_not_ready_in_time_is_reported_without_traceback(tmp_path):
    path, _ = cluster_config(tmp_path)
    res = run("shared.cli", "up", "-c", str(path), "--timeout", "0.2")
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    assert "robion up: cluster not ready within" in res.stderr, res.stderr
