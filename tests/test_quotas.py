"""The control plane's traffic step: quotas from the config's populations, limits and headroom."""

import logging

from services.controlplane.traffic import assign
from shared.config import config_from_dict

PLACEMENT = {"ex0": ["A", "B"], "ex1": ["A", "B"]}


def cluster(limit=4, **control):
    return config_from_dict({
        "models": [{"name": "A", "arch": "toy", "robots": 6, "limit": limit},
                   {"name": "B", "arch": "toy", "robots": 2, "limit": limit}],
        "executors": [{"name": "ex0", "models": ["A", "B"]}, {"name": "ex1", "models": ["A", "B"]}],
        "control": control})


def per_executor(robots):
    return {ex: sum(r.get(ex, 0) for r in robots.values()) for ex in PLACEMENT}


def test_full_limits_fill_both_gpus():
    q = assign(cluster(), PLACEMENT)
    assert q.result.strategy == "ip" and q.result.feasible
    assert per_executor(q.robots) == {"ex0": 4, "ex1": 4}
    assert q.limits == {"A": 4, "B": 4}


def test_headroom_that_cannot_hold_the_robots_plans_to_the_full_limits_and_says_so(caplog):
    """No plan keeps 75% of each limit (3 + 3 robots a GPU for 8), but one within the limits themselves does:
    it used to split evenly, which in general puts a GPU over its measured limit."""
    with caplog.at_level(logging.WARNING, logger="robion.control"):
        q = assign(cluster(headroom=0.75), PLACEMENT)
    assert q.result.strategy == "ip" and q.result.feasible
    assert per_executor(q.robots) == {"ex0": 4, "ex1": 4}
    assert q.limits == {"A": 4, "B": 4}  # the routing table keeps reporting the measured C_i
    assert any("within headroom 0.75" in r.getMessage() and "short by" in r.getMessage() for r in caplog.records)


def test_robots_beyond_the_full_limits_are_split_evenly_and_said_so(caplog):
    with caplog.at_level(logging.ERROR, logger="robion.control"):
        q = assign(cluster(limit=3, headroom=0.75), PLACEMENT)
    assert q.result.strategy == "eps"  # every robot still has a GPU
    assert q.robots == {"A": {"ex0": 3, "ex1": 3}, "B": {"ex0": 1, "ex1": 1}}
    assert q.limits == {"A": 3, "B": 3}
    assert any("infeasible" in r.getMessage() and "short by" in r.getMessage() for r in caplog.records)


def test_headroom_with_room_plans_at_the_reduced_limit():
    q = assign(cluster(limit=8, headroom=0.5), PLACEMENT)
    # floor(8 x 0.5) = 4: the paper example, both GPUs full at the reduced limit, A kept whole on one.
    assert q.result.strategy == "ip" and q.result.feasible and q.result.objective == 4
    assert per_executor(q.robots) == {"ex0": 4, "ex1": 4}
    assert q.limits == {"A": 8, "B": 8}
