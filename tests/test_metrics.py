"""Every service serves /metrics with the documented names, and the values move under load."""

import re
import time
import urllib.request

import pytest

import numpy as np

from shared.client import RobionError, RobotClient
from shared.cluster import LocalCluster
from shared.config import load_config
from tests.helpers import cluster_config, free_ports


def scrape(port: int) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as resp:
        return resp.read().decode()


def value(text: str, name: str, **labels) -> float:
    total = 0.0
    for line in text.splitlines():
        if not line.startswith(name + "{") and not line.startswith(name + " "):
            continue
        if all(f'{k}="{v}"' in line for k, v in labels.items()):
            total += float(line.rsplit(" ", 1)[1])
    return total


@pytest.mark.parametrize("engine", ["monolithic", "robion"])
def test_metrics_endpoints_and_movement(tmp_path, engine):
    rm, cm, em = free_ports(3)
    path, data = cluster_config(tmp_path, executors=[{"name": "ex0", "device": "cpu", "models": ["toy-a", "toy-b"],
                                                      "metrics_port": em}], engine={"kind": engine, "max_batch": 2})
    data["router"]["metrics_port"] = rm
    data["control"]["metrics_port"] = cm
    import yaml
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    with LocalCluster(cfg, path, log_level="WARNING"):
        before = scrape(em)
        for name in ["robion_requests_total", "robion_request_duration_seconds", "robion_queue_wait_seconds",
                     "robion_slo_attainment_ratio", "robion_queue_depth", "robion_batch_size",
                     "robion_lockstep_duration_seconds", "robion_vlm_sm_level", "robion_executor_info",
                     "robion_gpu_memory_used_bytes", "robion_inference_count_total", "robion_execution_count_total",
                     "robion_stage_duration_seconds", "robion_slo_met_total"]:
            assert f"# TYPE {name}" in before or f"# HELP {name}" in before, name
        assert value(before, "robion_executor_info", executor="ex0", device="cpu") == 1
        # No lockstep yet: no SM level (an unlabelled gauge read 0, "restricted to no SMs", from the start).
        assert re.search(r"^robion_vlm_sm_level NaN$", before, re.M)
        # liveness is the control plane's series alone: the executor's own copy doubled every executor
        assert "robion_executor_up" not in before
        control = scrape(cm)
        for name in ["robion_executors_registered", "robion_executor_up", "robion_routing_table_version",
                     "robion_robots_assigned"]:
            assert f"# HELP {name}" in control, name
        assert value(control, "robion_executors_registered") == 1
        router = scrape(rm)
        for name in ["robion_router_requests_total", "robion_router_request_duration_seconds",
                     "robion_router_in_flight_requests", "robion_router_routing_table_version",
                     "robion_router_slo_met_total", "robion_router_slo_missed_total"]:
            assert f"# HELP {name}" in router, name
        # SLO series exist at 0 before any request: a ratio of two counters is empty while one has no series
        for text, prefix in ((before, "robion_slo"), (router, "robion_router_slo")):
            for kind in ("met", "missed"):
                assert re.search(rf'{prefix}_{kind}_total{{model="toy-b"}} 0\.0', text), (prefix, kind)

        with RobotClient(cfg.router.bind) as client:
            info = client.metadata()["toy-a"]
            rng = np.random.default_rng(0)
            images = {c: rng.integers(0, 256, info.image_shape, dtype=np.uint8) for c in info.cameras}
            state = rng.standard_normal(info.state_dim).astype(np.float32)
            for _ in range(12):
                client.infer("toy-a", images, state)
            try:
                client.infer("toy-a", images, np.zeros(2, np.float32))
            except RobionError:
                pass
            hellos_and_pings = value(scrape(rm), "robion_router_requests_total", model="", status="ok")
            client.ping()
            client.metadata(refresh=True)
            # Answered hellos and pings were not counted, their refusals were ("answers sent to robots").
            assert value(scrape(rm), "robion_router_requests_total", model="", status="ok") == hellos_and_pings + 2
        after = scrape(em)
        assert value(after, "robion_requests_total", model="toy-a", status="ok") == 12
        assert value(after, "robion_requests_total", model="toy-a", status="shape_mismatch") == 1
        assert value(after, "robion_request_duration_seconds_count", model="toy-a") == 12
        assert value(after, "robion_inference_count_total", model="toy-a") == 12
        assert 1 <= value(after, "robion_execution_count_total", model="toy-a") <= 12
        assert value(after, "robion_slo_met_total", model="toy-a") == 12
        router = scrape(rm)
        assert value(router, "robion_router_requests_total", model="toy-a", status="ok") == 12
        assert value(router, "robion_router_request_duration_seconds_count", model="toy-a") == 12
        assert value(router, "robion_router_slo_met_total", model="toy-a") == 12
        assert value(router, "robion_router_slo_missed_total", model="toy-a") == 1  # the executor's SHAPE_MISMATCH
        assert re.search(r"robion_router_routing_table_version \d", router)
        if engine == "robion":  # lockstep telemetry reaches the metrics within a heartbeat
            time.sleep(0.5)
            locksteps = value(scrape(em), "robion_lockstep_duration_seconds_count")
            assert locksteps >= value(after, "robion_execution_count_total", model="toy-a")
        assert re.search(r"^robion_vlm_sm_level NaN$", scrape(em), re.M)  # a CPU has no SMs to restrict


def test_dashboard_queries_only_metrics_the_services_define():
    import json
    import os

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    dash = json.load(open(os.path.join(root, "deploy", "grafana-dashboard.json")))
    source = "".join(open(os.path.join(root, "shared", "metrics.py")).read())
    names = set(re.findall(r'"(robion_[a-z_]+)"', source))
    used = {n for p in dash["panels"] for t in p["targets"] for n in re.findall(r"robion_[a-z_]+", t["expr"])}
    base = {re.sub(r"_(bucket|count|sum)$", "", n) for n in used}
    assert base <= names, base - names


def test_the_attainment_window_starts_again_for_a_model_a_reload_adds_or_changes():
    """The gauge kept a model's window across a reload that took it away and brought it back (or changed its deadline):
    after an overload, a perfect run afterwards still read 7%. Its series also did not come back with the model."""
    from shared.metrics import ExecutorMetrics

    m = ExecutorMetrics("ex0", "cpu", {"a": 0.5, "b": 0.5}, window=10)
    reg = m.registry

    def ratio(model):
        return reg.get_sample_value("robion_slo_attainment_ratio", {"model": model})

    for _ in range(5):
        m.observe_result("b", "overloaded", 0.01, 0, 0, 0)
    m.observe_result("a", "ok", 0.01, 0, 0, 0)
    m.observe_result("a", "ok", 0.9, 0, 0, 0)  # late
    assert (ratio("a"), ratio("b")) == (0.5, 0.0)
    m.serve_models({"a": 0.5})  # b moved away
    assert ratio("b") is None and reg.get_sample_value("robion_queue_depth", {"model": "b"}) is None
    m.observe_result("b", "ok", 0.01, 0, 0, 0)  # a straggler of the old engine: counted, but no gauge series back
    assert ratio("b") is None and reg.get_sample_value("robion_slo_met_total", {"model": "b"}) == 1
    m.serve_models({"a": 1.0, "b": 0.5})  # b back, a at another deadline: both start again
    assert (ratio("a"), ratio("b")) == (1.0, 1.0)
    m.observe_result("b", "ok", 0.01, 0, 0, 0)
    m.observe_result("a", "ok", 0.9, 0, 0, 0)  # within a's new deadline
    assert (ratio("a"), ratio("b")) == (1.0, 1.0)
    m.serve_models({"a": 1.0, "b": 0.5})  # the same settings again (every heartbeat): nothing starts again
    m.observe_result("a", "ok", 2.0, 0, 0, 0)
    assert ratio("a") == 0.5


def test_batch_sizes_up_to_the_largest_max_batch_have_a_bucket():
    """Buckets stopped at 32 while engine.max_batch may be 256: a batch of 64, 128 or 256 fell only into +Inf, and
    histogram_quantile read every one of them as 32."""
    from shared.config import MAX_BATCH
    from shared.metrics import BATCH_BUCKETS

    assert max(BATCH_BUCKETS) >= MAX_BATCH and all(2 ** i in BATCH_BUCKETS for i in range(MAX_BATCH.bit_length()))


def test_a_metrics_port_equal_to_a_zeromq_port_is_a_clash_and_a_taken_one_is_found(tmp_path):
    """The router's metrics server took router.backend's port first, and its bind then failed as 'address in use',
    blaming the backend address."""
    import socket

    from shared.cluster import metrics_port_clash, metrics_ports_taken

    path, data = cluster_config(tmp_path)
    backend_port = int(data["router"]["backend"].rsplit(":", 1)[1])
    data["router"]["metrics_port"] = backend_port
    import yaml
    path.write_text(yaml.safe_dump(data))
    assert metrics_port_clash(load_config(path)) == (
        f"metrics port {backend_port} is both router.backend's and the router's on this host; give one another "
        "metrics_port (executors default to 9110 + their index; 0 disables)")
    (port,) = free_ports(1)
    data["router"]["metrics_port"] = port
    path.write_text(yaml.safe_dump(data))
    assert metrics_ports_taken(load_config(path)) == []
    with socket.socket() as holder:
        holder.bind(("0.0.0.0", port))
        holder.listen()
        assert metrics_ports_taken(load_config(path)) == [
            f"metrics port {port} (the router's) is taken on this host (Address already in use)"]
