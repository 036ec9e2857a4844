"""The traffic controller: from populations, robot limits and live placement to per-executor robot quotas."""

from __future__ import annotations

import logging
from dataclasses import dataclass

from services.controlplane.solver import ModelDemand, PlanInputError, PlanProblem, PlanResult, solve, with_headroom
from shared.config import ClusterConfig

log = logging.getLogger("robion.control")


@dataclass
class Quotas:
    """Robots of each model per executor; empty when the config declares no populations."""

    robots: dict[str, dict[str, int]]  # model -> executor -> robots
    limits: dict[str, int]  # model -> C_i
    result: PlanResult | None = None


def assign(cfg: ClusterConfig, placement: dict[str, list[str]], measured: dict[str, int] | None = None) -> Quotas:
    """Solve the robot-to-GPU assignment over the executors alive now (``placement``: executor -> models).

    Each limit is first cut to ``control.headroom`` of C_i (``with_headroom``). When the
    integer program is infeasible the even split is used instead, so every robot still has
    a GPU, and the diagnosis is logged for the operator.
    """
    demands = {m.name: m for m in cfg.models if m.robots > 0}
    if cfg.control.strategy == "none" or not demands:
        return Quotas({}, {})
    measured = measured or {}
    limit = {n: m.limit if m.limit is not None else measured.get(n) for n, m in demands.items()}
    # A model without a limit (none configured, not measured yet, or added by an apply) cannot be planned:
    # its robots are spread round-robin per request. The others keep their assignment; giving it up for
    # the whole cluster took pinning and batching from every model because of one.
    missing = [n for n, c in limit.items() if c is None]
    if missing:
        log.warning("no robot limit for %s: their robots are spread round-robin per request; planning the "
                    "other models without them", missing)
    executors = list(placement)
    hosts: dict[str, list[int]] = {}
    for j, name in enumerate(executors):
        for model in placement[name]:
            hosts.setdefault(model, []).append(j)
    # A model no live, serving executor hosts (its hosts drained, crashed or not registered yet)
    # has no route, so its robots are answered UNAVAILABLE until a host is back. Planning it would
    # make the whole problem invalid and drop every other model's assignment with it.
    unhosted = [n for n in demands if n not in hosts]
    if unhosted:
        log.warning("no serving executor hosts %s: planning the other models without them", unhosted)
    planned = [m for m in demands.values() if m.name in hosts and limit[m.name] is not None]
    if not planned:
        return Quotas({}, {})
    try:
        problem = with_headroom(PlanProblem(len(executors), tuple(
            ModelDemand(m.name, limit[m.name], m.robots, tuple(hosts[m.name])) for m in planned)),
            cfg.control.headroom)
    except PlanInputError as exc:
        log.error("cannot plan the traffic: %s", exc)
        return Quotas({}, {})
    try:
        result = solve(problem, cfg.control.strategy, time_limit_s=cfg.control.solve_time_limit_s)
    except PlanInputError as exc:
        # Limits the integer program cannot state exactly (e.g. their least common multiple
        # overflows int64): the even split needs no such arithmetic and still gives every robot a GPU.
        log.error("cannot solve the traffic assignment: %s; splitting robots evenly instead", exc)
        result = solve(problem, "eps")
    if not result.assignment:
        log.error("traffic assignment is infeasible: %s; splitting robots evenly instead", result.diagnosis)
        result = solve(problem, "eps")
    elif not result.feasible:
        log.warning("traffic assignment exceeds GPU limits: %s", result.diagnosis)
    robots = {m: {executors[j]: n for j, n in per_gpu.items() if n} for m, per_gpu in result.assignment.items()}
    log.info("traffic assignment (%s, objective %s): %s", result.strategy, result.objective, robots)
    return Quotas(robots, {n: int(c) for n, c in limit.items() if c is not None}, result)
