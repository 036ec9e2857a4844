"""Robot limits measured by the executors through their own engine, cached, and used by the solver."""

import json
import os

import yaml

from services.executor.limits import owned_models
from shared.cluster import LocalCluster, control_status
from shared.config import config_from_dict, load_config
from tests.helpers import cluster_config


def test_each_model_is_measured_by_its_first_host():
    cfg = config_from_dict({"models": [{"name": "a", "arch": "toy"}, {"name": "b", "arch": "toy"}],
                            "executors": [{"name": "e0", "models": ["a"]}, {"name": "e1", "models": ["a", "b"]}]})
    assert owned_models(cfg, "e0", ["a"]) == ["a"]
    assert owned_models(cfg, "e1", ["a", "b"]) == ["b"]


def test_limits_are_measured_cached_and_solved_with(tmp_path):
    path, data = cluster_config(tmp_path)
    data["models"][0].update(robots=5)
    data["models"][1].update(robots=2)
    data["control"]["limits"] = {"auto": True, "epochs": 1, "duration_s": 1.0, "max_robots": 4, "progress": False}
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    cache = os.path.join(data["control"]["state_dir"], "limits.json")
    with LocalCluster(cfg, path, log_level="WARNING"):
        status = control_status(cfg.control.bind)
        assert status["limits"] == {"toy-a": 4, "toy-b": 4}  # capped by max_robots: the toy model is fast
        quotas = status["table"]["quotas"]
        assert sum(quotas["toy-a"].values()) == 5 and sum(quotas["toy-b"].values()) == 2
        assert all(sum(q.get(ex, 0) for q in quotas.values()) <= 4 for ex in ("ex0", "ex1"))
    entries = json.load(open(cache))
    assert len(entries) == 1  # both models share one key: same architecture, size, rate and deadline
    (key, entry), = entries.items()
    assert key.startswith("cpu|toy:tiny|2Hz|mb2|500ms|monolithic") and entry["limit"] == 4
    assert [p["robots"] for p in entry["points"]][:3] == [1, 2, 4]
    mtime = os.path.getmtime(cache)
    with LocalCluster(cfg, path, log_level="WARNING"):  # a restart reuses the cache
        assert control_status(cfg.control.bind)["limits"] == {"toy-a": 4, "toy-b": 4}
    assert os.path.getmtime(cache) == mtime
