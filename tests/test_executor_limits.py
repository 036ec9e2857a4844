"""The executor's robot-limit cache (services/executor/limits.py) when limits.json was edited by hand.

docs/operations.md: a limit that is not a positive integer (0, negative, a fraction, inf,
NaN, e.g. from a hand-edited limits.json) is ignored. An executor reading one from its
cache must not crash at start-up nor report it: it measures the limit again.
"""

import json
import logging
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

from services.executor.hosting import ModelStore
from services.executor.limits import device_name, limit_key, measure_limits
from shared.config import load_config
from tests.helpers import ROOT, cluster_config, executor_exit, free_ports

CPU = torch.device("cpu")


def _setup(tmp_path):
    path, data = cluster_config(tmp_path, executors=[{"name": "ex0", "device": "cpu", "models": ["toy-a", "toy-b"]}])
    data["control"]["limits"] = {"auto": True, "epochs": 1, "duration_s": 0.5, "max_robots": 2, "progress": False}
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    hosted = ModelStore(CPU).load([cfg.model("toy-a")])
    served = hosted.models["toy-a"]
    key = limit_key(device_name(CPU), served.model.arch, "tiny", 2.0, cfg.engine.max_batch, 500.0, cfg.engine.kind,
                    cfg.control.limits.target)
    return cfg, hosted, key, Path(cfg.control.state_dir) / "limits.json"


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), 0, -3, 2.5, None, "4", True])
def test_an_unusable_cached_limit_is_measured_again(tmp_path, caplog, bad):
    cfg, hosted, key, cache = _setup(tmp_path)
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text(json.dumps({key: {"limit": bad, "measured_s": 1.0}}))  # NaN / Infinity: Python's JSON allows them
    with caplog.at_level(logging.WARNING, logger="robion.executor"):
        limits = measure_limits(cfg, "ex0", hosted.models, CPU)
    assert limits == {"toy-a": 2}  # measured (capped by max_robots: the toy model is fast)
    assert json.loads(cache.read_text())[key]["limit"] == 2  # the bad entry is replaced
    assert any("limits.json" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("content", ["[1, 2]", '{"k": 3}', "not json"])
def test_a_cache_file_of_another_shape_is_measured_over(tmp_path, content):
    cfg, hosted, key, cache = _setup(tmp_path)
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text(content)
    assert measure_limits(cfg, "ex0", hosted.models, CPU) == {"toy-a": 2}
    assert json.loads(cache.read_text())[key]["limit"] == 2


def test_a_valid_cached_limit_is_reused(tmp_path):
    cfg, hosted, key, cache = _setup(tmp_path)
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text(json.dumps({key: {"limit": 7}}))
    assert measure_limits(cfg, "ex0", hosted.models, CPU) == {"toy-a": 7}


@pytest.mark.parametrize("value", ["abc", "0", "-2", "1.5", "99999999999999999999"])
def test_a_bad_cpu_thread_count_stops_the_executor_with_the_variable_named(tmp_path, value):
    """ROBION_CPU_THREADS=abc ended the executor with a ValueError traceback (and 0 with torch's RuntimeError)."""
    import os

    path, _ = cluster_config(tmp_path)
    res = executor_exit(path, env={**os.environ, "ROBION_CPU_THREADS": value})
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    assert "ROBION_CPU_THREADS" in res.stderr and "Traceback" not in res.stderr, res.stderr[-2000:]


def test_a_replica_named_past_the_socket_identity_limit_stops_with_the_flag_named(tmp_path):
    """A replica outside the config (--name, --models) skipped the 255-byte identity check a configured executor
    gets at load: it ended with a ZMQError traceback when it bound its sockets."""
    path, _ = cluster_config(tmp_path)
    res = subprocess.run([sys.executable, "-m", "services.executor.main", "-c", str(path), "--name", "r" * 300,
                          "--models", "toy-a"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    assert "--name: expected at most 255 bytes" in res.stderr and "Traceback" not in res.stderr, res.stderr[-2000:]


@pytest.mark.parametrize("device", ["cuda1", "gpu:0", "cuda:x"])
def test_a_bad_device_override_stops_the_executor_with_the_flag_named(tmp_path, device):
    """--device cuda1 ended the executor with torch's RuntimeError traceback; the config refuses the same value."""
    path, _ = cluster_config(tmp_path)
    res = executor_exit(path, "--device", device)
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    assert "--device" in res.stderr and "Traceback" not in res.stderr, res.stderr[-2000:]


@pytest.mark.skipif(torch.cuda.device_count() > 0, reason="needs a host where cuda:0 is absent")
@pytest.mark.parametrize("where", ["override", "config", "interdisagg"])
def test_an_absent_gpu_stops_the_executor_with_the_device_named(tmp_path, where):
    """cuda:0 on a host without a GPU (or cuda:7 on one with 4) passes the config's check, and the executor died
    with a traceback from torch's first CUDA call. It now exits 2 naming the device and what the host has."""
    extra: list[str] = []
    if where == "override":
        path, _ = cluster_config(tmp_path)
        extra = ["--device", "cuda:0"]
    elif where == "config":
        path, _ = cluster_config(tmp_path, executors=[{"name": "ex0", "device": "cuda:0", "models": ["toy-a", "toy-b"]}])
    else:
        path, _ = cluster_config(tmp_path, engine={"kind": "interdisagg", "max_batch": 2,
                                                   "vlm_devices": "cpu", "action_devices": "0"})
    res = executor_exit(path, *extra)
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    named = "engine.action_devices cuda:0" if where == "interdisagg" else "device cuda:0"
    assert named in res.stderr and "no CUDA GPU is visible" in res.stderr, res.stderr[-2000:]
    assert "Traceback" not in res.stderr, res.stderr[-2000:]


def test_a_reload_reports_the_limit_of_the_new_settings(tmp_path):
    """A limit holds for the rate and deadline it was measured at. After a live apply changed a model's rate, the
    reloaded executor registered again with its start-up limit (the old rate's), and the plane planned with it."""
    import time
    from dataclasses import asdict, replace

    from shared import control
    from tests.test_executor_io import Harness

    h = Harness(tmp_path, models=("toy-a",), control_plane=True,
                control={"bind": f"tcp://127.0.0.1:{free_ports(1)[0]}", "heartbeat_s": 0.05, "metrics_port": 0,
                         "state_dir": str(tmp_path / "state"), "limits": {"auto": True, "progress": False}})
    try:
        cfg, mc = h.cfg, h.cfg.model("toy-a")

        def key(hz: float) -> str:
            return limit_key("cpu", "toy", mc.size, hz, cfg.engine.max_batch, mc.slo_ms, cfg.engine.kind,
                             cfg.control.limits.target)

        Path(cfg.control.state_dir).mkdir(parents=True, exist_ok=True)
        (Path(cfg.control.state_dir) / "limits.json").write_text(json.dumps({key(2.0): {"limit": 40},
                                                                            key(10.0): {"limit": 8}}))
        h.io.limits = measure_limits(cfg, "ex0", h.slot.engine.models, CPU)  # as main() does at start-up
        assert h.io.limits == {"toy-a": 40}

        def registration_after_load(model) -> dict:
            h.control_messages(0.2)
            h.control.send_multipart([b"ex0", control.pack("load", models=[asdict(model)])])
            end = time.monotonic() + 30
            while time.monotonic() < end:
                for msg in h.control_messages(0.1):
                    if msg.get("kind") == "register":
                        return msg
            raise AssertionError("no registration after the load")

        assert registration_after_load(replace(mc, hz=10.0))["limits"] == {"toy-a": 8}
        # Settings nothing was measured at: no limit (the plane plans the model without one), not the old one.
        assert registration_after_load(replace(mc, hz=5.0))["limits"] == {}
    finally:
        h.close()


def test_limit_measurement_writes_nothing_to_the_serving_telemetry_file(tmp_path):
    tele = tmp_path / "telemetry.jsonl"
    path, data = cluster_config(tmp_path, models=[{"name": "toy-a", "arch": "toy", "size": "tiny", "slo_ms": 100}],
                                executors=[{"name": "ex0", "device": "cpu", "models": ["toy-a"]}],
                                engine={"kind": "robion", "max_batch": 2, "telemetry_file": str(tele)})
    data["control"]["limits"] = {"auto": True, "epochs": 1, "duration_s": 0.5, "max_robots": 4, "progress": False}
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    assert measure_limits(cfg, "ex0", ModelStore(CPU).load([cfg.model("toy-a")]).models, CPU)
    assert not tele.exists() or not tele.read_text().strip(), "simulated locksteps in the serving telemetry"


def test_a_stop_during_limit_measurement_ends_the_executor_promptly(tmp_path):
    """The start-up capacity search (minutes with the defaults) never looked at the stop: SIGTERM was honoured only
    once it was over, long after a container's grace period."""
    import subprocess
    import sys

    from tests.helpers import ROOT, sigterm_after_line

    path, data = cluster_config(tmp_path, models=[{"name": "pi", "arch": "pi0", "size": "tiny", "slo_ms": 156}],
                                executors=[{"name": "ex0", "device": "cpu", "models": ["pi"]}])
    data["control"]["limits"] = {"auto": True, "epochs": 3, "duration_s": 3.0, "max_robots": 64, "progress": False}
    path.write_text(yaml.safe_dump(data))
    proc = subprocess.Popen([sys.executable, "-m", "services.executor.main", "-c", str(path), "--name", "ex0"],
                            cwd=ROOT, stderr=subprocess.PIPE, text=True)
    try:
        sigterm_after_line(proc, proc.stderr, "measuring the robot limit", 1.0)
        assert proc.wait(timeout=10) == 0  # docker's default grace period; one epoch is 3 s here
        assert not (tmp_path / "state" / "limits.json").exists()  # nothing cached from the cut search
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _write_entries(path: str, prefix: str, n: int, start) -> None:
    from services.executor.limits import LimitCache

    cache = LimitCache(path)
    start.wait(60)
    for i in range(n):
        cache.write(f"{prefix}-{i}", {"limit": i + 1})


def test_executors_writing_the_limit_cache_at_once_keep_every_entry(tmp_path):
    """Executors on other GPUs write one limits.json. Each write read, changed and replaced the file: two
    overlapping writes dropped each other's new entries (526 of 1000 kept), to be measured again at the next start."""
    import multiprocessing

    path = str(tmp_path / "state" / "limits.json")
    ctx = multiprocessing.get_context("spawn")
    start = ctx.Barrier(2)
    writers = [ctx.Process(target=_write_entries, args=(path, name, 300, start)) for name in ("gpu0", "gpu1")]
    for w in writers:
        w.start()
    for w in writers:
        w.join(120)
        assert w.exitcode == 0
    assert len(json.loads(Path(path).read_text())) == 600


def test_a_limit_cache_that_cannot_be_written_keeps_the_measured_limit(tmp_path, caplog):
    """A state_dir under a file (or read-only, or full) ended the executor with a traceback after the whole
    capacity search, and a supervisor's restart searched again and died again."""
    from services.executor.limits import LimitCache

    (tmp_path / "not-a-dir").write_text("")
    cache = LimitCache(tmp_path / "not-a-dir" / "state" / "limits.json")
    with caplog.at_level(logging.WARNING, logger="robion.executor"):
        assert cache.write("k", {"limit": 3}) is False
    assert "could not write the robot limit cache" in caplog.text
    assert cache.read() == {}


def test_cached_limits_are_reported_for_models_another_executor_was_first_to_host(tmp_path):
    """An apply moves toy-b to ex1; ex1's file still names ex0 as toy-b's first host, so its reload reported no
    limit for toy-b although one was cached for those settings, and the plane planned toy-b without one. Only a
    measurement is left to the first host."""
    from services.executor.engine import ServedModel, resolve_kind
    from shared.models import build_model

    path, _ = cluster_config(tmp_path, control={"bind": f"tcp://127.0.0.1:{free_ports(1)[0]}", "metrics_port": 0,
                                                "state_dir": str(tmp_path / "state"), "limits": {"auto": True}})
    cfg = load_config(path)  # ex0: toy-a, toy-b; ex1: toy-a
    mc = cfg.model("toy-b")
    key = limit_key("cpu", "toy", mc.size, mc.hz, cfg.engine.max_batch, mc.slo_ms,
                    resolve_kind(cfg.engine.kind, CPU), cfg.control.limits.target)
    Path(cfg.control.state_dir).mkdir(parents=True)
    (Path(cfg.control.state_dir) / "limits.json").write_text(json.dumps({key: {"limit": 12}}))
    served = {"toy-b": ServedModel("toy-b", build_model("toy", "tiny"), mc.slo_ms / 1e3)}
    assert measure_limits(cfg, "ex1", served, CPU, measure=False) == {"toy-b": 12}
    # At start-up too (measure=True): ex1 reports the cached limit, and measures nothing (toy-b is ex0's to measure).
    assert measure_limits(cfg, "ex1", served, CPU) == {"toy-b": 12}
    (Path(cfg.control.state_dir) / "limits.json").write_text("{}")
    assert measure_limits(cfg, "ex1", served, CPU) == {}


def test_the_key_names_a_network_or_engine_setting_away_from_its_default():
    """A limit measured over one network or engine setting was reused for another (the key left both out)."""
    from shared.config import EngineConfig

    base = limit_key("cpu", "toy", "tiny", 2.0, 2, 500.0, "robion", 0.98)
    assert limit_key("cpu", "toy", "tiny", 2.0, 2, 500.0, "robion", 0.98, "wifi7", EngineConfig()) == base
    assert limit_key("cpu", "toy", "tiny", 2.0, 2, 500.0, "robion", 0.98, "slow_cloud") == base + "|net:slow_cloud"
    assert limit_key("cpu", "toy", "tiny", 2.0, 2, 500.0, "robion", 0.98, "wifi7",
                     EngineConfig(shed_late=True, sm_policy="none")) == base + "|shed_late=True|sm_policy=none"


def test_a_limit_cached_at_the_searchs_cap_is_measured_again_under_a_higher_cap(tmp_path):
    """A search stopped by max_robots found the cap, not the GPU's limit: with the cap raised, the cached value
    was reused and the limit never grew."""
    cfg, hosted, key, cache = _setup(tmp_path)  # max_robots 2; the toy model passes it
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text(json.dumps({key: {"limit": 1, "max_robots": 1}}))
    assert measure_limits(cfg, "ex0", hosted.models, CPU) == {"toy-a": 2}
    entry = json.loads(cache.read_text())[key]
    assert entry["limit"] == 2 and entry["max_robots"] == 2
    cache.write_text(json.dumps({key: {"limit": 1, "max_robots": 2}}))  # below its own cap: the GPU's limit
    assert measure_limits(cfg, "ex0", hosted.models, CPU) == {"toy-a": 1}


def test_a_model_that_misses_its_deadline_with_one_robot_gets_no_limit(tmp_path, caplog):
    """A search where even 1 robot fails the target used to report and cache a limit of 1, which promised a robot
    the model cannot serve and was reused by every later start. Now nothing is reported or cached."""
    path, data = cluster_config(tmp_path, models=[{"name": "toy-a", "arch": "toy", "size": "tiny", "slo_ms": 0.001}],
                                executors=[{"name": "ex0", "device": "cpu", "models": ["toy-a"]}])
    data["control"]["limits"] = {"auto": True, "epochs": 1, "duration_s": 0.5, "max_robots": 4, "progress": False}
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    hosted = ModelStore(CPU).load([cfg.model("toy-a")])
    with caplog.at_level(logging.WARNING, logger="robion.executor"):
        assert measure_limits(cfg, "ex0", hosted.models, CPU) == {}
    cache = Path(cfg.control.state_dir) / "limits.json"
    assert not cache.exists() or json.loads(cache.read_text()) == {}
    assert any("not even 1 robot" in r.getMessage() for r in caplog.records)
    # A 1 cached by the code before (its own points show the miss) is measured again, not trusted.
    key = limit_key(device_name(CPU), "toy", "tiny", 2.0, cfg.engine.max_batch, 0.001, cfg.engine.kind,
                    cfg.control.limits.target)
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text(json.dumps({key: {"limit": 1, "max_robots": 4, "points": [{"robots": 1, "slo_attainment": 0.0}]}}))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="robion.executor"):
        assert measure_limits(cfg, "ex0", hosted.models, CPU) == {}
    assert any("missed the target at that count" in r.getMessage() for r in caplog.records)


def test_a_model_called_less_often_than_once_per_measuring_epoch_is_measured_over_one_period(tmp_path):
    """At 0.5 Hz and duration_s 0.5 an epoch sends nothing: the harness refuses that, and the executor's start
    crashed on it (exit 1, restarted in a loop)."""
    path, data = cluster_config(tmp_path, executors=[{"name": "ex0", "device": "cpu", "models": ["toy-a"]}],
                                models=[{"name": "toy-a", "arch": "toy", "size": "tiny", "seed": 0, "slo_ms": 500,
                                         "hz": 0.5}])
    data["control"]["limits"] = {"auto": True, "epochs": 1, "duration_s": 0.5, "max_robots": 2, "progress": False}
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    hosted = ModelStore(CPU).load([cfg.model("toy-a")])
    assert measure_limits(cfg, "ex0", hosted.models, CPU) == {"toy-a": 2}
