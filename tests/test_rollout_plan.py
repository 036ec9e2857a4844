"""What `robion ctl apply` may change live (the rest is refused: it is read at start-up)."""

from services.controlplane.rollout import restart_only_changes
from shared.config import config_from_dict

BASE = {
    "models": [{"name": "a", "arch": "pi0", "robots": 4}, {"name": "b", "arch": "xr0", "robots": 2}],
    "executors": [{"name": "ex0", "models": ["a"]}, {"name": "ex1", "models": ["b"]}],
}


def cfg(**changes):
    data = {**BASE, **changes}
    return config_from_dict(data)


def test_placement_populations_and_strategy_are_live():
    old = cfg()
    new = cfg(models=[{"name": "a", "arch": "pi0", "robots": 9, "hz": 4}, {"name": "b", "arch": "xr0", "robots": 2}],
              executors=[{"name": "ex0", "models": ["a", "b"]}, {"name": "ex1", "models": ["b"]},
                         {"name": "ex2", "models": ["a"], "device": "cuda:1"}],
              control={"strategy": "eps", "solve_time_limit_s": 1.0, "headroom": 0.9})
    assert restart_only_changes(old, new) == []


def test_start_up_settings_are_named():
    old = cfg()
    new = cfg(engine={"kind": "robion", "max_batch": 4}, router={"request_timeout_s": 5.0},
              control={"heartbeat_s": 1.0, "limits": {"target": 0.95}},
              executors=[{"name": "ex0", "models": ["a"], "device": "cuda:0"}, {"name": "ex1", "models": ["b"]}])
    assert restart_only_changes(old, new) == [
        "engine.kind: 'monolithic' -> 'robion'", "engine.max_batch: 2 -> 4", "router.request_timeout_s: 30.0 -> 5.0",
        "control.heartbeat_s: 0.5 -> 1.0", "control.limits.target: 0.98 -> 0.95", "executors.ex0.device: 'cpu' -> 'cuda:0'"]

