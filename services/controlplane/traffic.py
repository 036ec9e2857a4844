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

    Each limit is first cut to ``control.headroom`` of C_i (``with_headroom``). The integer program
    returns its greedy plan when CP-SAT finds none better within ``control.solve_time_limit_s``; only
    without any plan (infeasible, or a time-out where the greedy plan got stuck) is the even split used
    instead, so every robot still has a GPU, and the diagnosis is logged for the operator.
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
        full = PlanProblem(len(executors), tuple(
            ModelDemand(m.name, limit[m.name], m.robots, tuple(hosts[m.name])) for m in planned))
        problem = with_headroom(full, cfg.control.headroom)
    except PlanInputError as exc:
        log.error("cannot plan the traffic: %s", exc)
        return Quotas({}, {})
    try:
        result = solve(problem, cfg.control.strategy, time_limit_s=cfg.control.solve_time_limit_s)
        if not result.assignment and problem != full:
            # No plan keeps the headroom's slack: one within the measured limits themselves still beats the
            # even split below, which can put a GPU far over its limit.
            log.warning("no traffic assignment within headroom %g of the robot limits (%s); planning to the "
                        "full limits", cfg.control.headroom, result.diagnosis)
            result = solve(full, cfg.control.strategy, time_limit_s=cfg.control.solve_time_limit_s)
    except PlanInputError as exc:
        # Limits the integer program cannot state exactly (e.g. their least common multiple
        # overflows int64) and no greedy plan: the even split needs no such arithmetic and still gives
        # every robot a GPU.
        log.error("cannot solve the traffic assignment: %s; splitting robots evenly instead", exc)
        result = solve(problem, "eps")
    if not result.assignment:
        what = "found no assignment in time" if result.status == "unknown" else "is infeasible"
        log.error("traffic assignment %s: %s; splitting robots evenly instead", what, result.diagnosis)
        result = solve(problem, "eps")
    elif not result.feasible:
        log.warning("traffic assignment exceeds GPU limits: %s", result.diagnosis)
    robots = {m: {executors[j]: n for j, n in per_gpu.items() if n} for m, per_gpu in result.assignment.items()}
    log.info("traffic assignment (%s, objective %s): %s", _describe(result), result.objective, robots)
    return Quotas(robots, {n: int(c) for n, c in limit.items() if c is not None}, result)


def _describe(result: PlanResult) -> str:
    """Strategy, and for ip where the plan came from and whether it is proven optimal."""
    if result.strategy != "ip":
        return result.strategy
    # "greedy": CP-SAT found no better plan within control.solve_time_limit_s (raise it for a better one).
    proof = "proven optimal" if result.optimal else f"not proven optimal, lower bound {result.best_bound}"
    return f"ip, {result.source} plan, {proof}"
