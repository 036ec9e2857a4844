"""Traffic controller: how many robots of each model every GPU serves (paper §4.2).

Given G GPUs and models i with robot limit C_i (the most robots of model i one GPU
sustains at the target SLO), population N_i and the set of GPUs hosting it, choose
integers r_ij (robots of model i served by GPU j, 0 where j does not host i) with

    (1) sum_j r_ij = N_i                 every model's robots are all served
    (2) sum_i r_ij / C_i <= 1            no GPU is pushed past its limit
    (3) minimize sum_j sum_{i<k} r_ij * r_kj

The objective is zero exactly when every GPU serves one model, so minimizing it keeps
each model's traffic concentrated in few FIFO queues (large batches) while (2) splits a
model over more GPUs only as far as the limits force.

Three strategies share one result type:
  * ``ip``  -- the integer program above, solved with OR-Tools CP-SAT;
  * ``smg`` -- single model per GPU: each model wholly on one hosting GPU;
  * ``eps`` -- even population split of every model over its hosting GPUs.
``smg`` and ``eps`` exist for comparison (paper Fig. 6a/6b) and may break (2); their
``feasible`` flag says whether they do.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections import deque
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Iterable, Mapping, Sequence

from ortools.sat.python import cp_model

log = logging.getLogger(__name__)

STRATEGIES = ("ip", "smg", "eps")
# Stays under the 10 s budget for 32 models x 16 GPUs including model building; the result
# says whether optimality was proven within it.
DEFAULT_TIME_LIMIT_S = 8.0

# CP-SAT rejects models whose linear constraints could overflow int64 when summed at
# the variables' bounds; stay well below that so the exact scaled constraint (2) is safe.
_MAX_SCALED_ACTIVITY = 2**60


class PlanInputError(ValueError):
    """Invalid planning input; ``path`` names the offending field (``models.A.limit``)."""

    def __init__(self, path: str, message: str) -> None:
        self.path = path
        self.detail = message
        super().__init__(f"{path}: {message}" if path else message)


@dataclass(frozen=True)
class ModelDemand:
    """One served model: its per-GPU robot limit C_i, population N_i and hosting GPUs."""

    name: str
    limit: int
    robots: int
    gpus: tuple[int, ...]

    @property
    def gpu_equivalents(self) -> Fraction:
        """N_i / C_i: how many fully loaded GPUs this model's population fills."""
        return Fraction(self.robots, self.limit)


@dataclass(frozen=True)
class PlanProblem:
    """Input of the traffic controller. Models keep their given order in all outputs."""

    num_gpus: int
    models: tuple[ModelDemand, ...]

    def __post_init__(self) -> None:
        validate_problem(self)

    def model(self, name: str) -> ModelDemand:
        for m in self.models:
            if m.name == name:
                return m
        raise KeyError(name)

    def hosted_on(self, gpu: int) -> list[ModelDemand]:
        return [m for m in self.models if gpu in m.gpus]


def with_headroom(problem: PlanProblem, headroom: float) -> PlanProblem:
    """The same problem with every limit C_i cut to floor(C_i * headroom), at least 1.

    A measured C_i is the robot count at which one GPU just holds the target SLO
    attainment; planning a fleet right up to it leaves no slack for arrival bursts or
    co-located models. ``headroom`` < 1 keeps that slack. The product is taken on the
    decimal value (0.29 x 100 is 29, not 28.999...)."""
    if not 0 < headroom <= 1:
        raise PlanInputError("headroom", f"expected a share in (0, 1], got {headroom!r}")
    if headroom == 1:
        return problem
    share = Fraction(repr(float(headroom)))
    return PlanProblem(problem.num_gpus, tuple(
        ModelDemand(m.name, max(1, math.floor(m.limit * share)), m.robots, m.gpus) for m in problem.models))


@dataclass
class PlanResult:
    """Outcome of one strategy.

    ``assignment`` maps every model name to ``{gpu_index: robots}`` holding only the
    GPUs with a positive robot count (a model with no robots maps to ``{}``); it is
    empty when no assignment exists (IP infeasible or timed out without a solution).
    ``objective`` is the value of (3) for the assignment, None without one.
    ``feasible`` means the assignment exists and respects every GPU limit (2).
    ``optimal`` is True only when CP-SAT proved the objective optimal.
    """

    strategy: str
    assignment: dict[str, dict[int, int]]
    objective: int | None
    feasible: bool
    optimal: bool
    status: str  # optimal | feasible | overloaded | infeasible | unknown
    solve_time_s: float
    diagnosis: str | None = None
    best_bound: float | None = None  # CP-SAT's proven lower bound on the objective
    gpu_load: list[Fraction] = field(default_factory=list)  # sum_i r_ij / C_i per GPU

    def to_json_dict(self) -> dict[str, object]:
        """The ``robion plan --json`` shape: assignment, objective, feasible only."""
        return {
            "assignment": {m: {str(g): r for g, r in gpus.items()} for m, gpus in self.assignment.items()},
            "objective": self.objective,
            "feasible": self.feasible,
        }


# --------------------------------------------------------------------------- validation


def _is_int(x: object) -> bool:
    # bool is an int subclass; `limit: true` in YAML is a mistake, not 1.
    return isinstance(x, int) and not isinstance(x, bool)


def validate_problem(problem: PlanProblem) -> None:
    """Raise PlanInputError (with a field path) for inputs the solver cannot take."""
    if not _is_int(problem.num_gpus) or problem.num_gpus < 1:
        raise PlanInputError("gpus", f"expected a positive integer, got {problem.num_gpus!r}")
    seen: set[str] = set()
    for m in problem.models:
        base = f"models.{m.name}"
        if m.name in seen:
            raise PlanInputError(base, "duplicate model name")
        seen.add(m.name)
        if not _is_int(m.limit) or m.limit < 1:
            raise PlanInputError(f"{base}.limit", f"expected a positive integer, got {m.limit!r}")
        if not _is_int(m.robots) or m.robots < 0:
            raise PlanInputError(f"{base}.robots", f"expected a non-negative integer, got {m.robots!r}")
        for k, g in enumerate(m.gpus):
            if not _is_int(g) or not 0 <= g < problem.num_gpus:
                raise PlanInputError(
                    f"{base}.gpus[{k}]",
                    f"expected a GPU index in 0..{problem.num_gpus - 1}, got {g!r}",
                )
        if len(set(m.gpus)) != len(m.gpus):
            raise PlanInputError(f"{base}.gpus", f"duplicate GPU index in {list(m.gpus)}")
        if m.robots > 0 and not m.gpus:
            raise PlanInputError(
                f"{base}.gpus", f"model has {m.robots} robots but no GPU hosts it; place it on at least one GPU"
            )


# --------------------------------------------------------------------------- helpers


def objective_value(problem: PlanProblem, assignment: Mapping[str, Mapping[int, int]]) -> int:
    """Objective (3): sum over GPUs of products r_ij * r_kj of distinct models."""
    total = 0
    for j in range(problem.num_gpus):
        counts = [assignment.get(m.name, {}).get(j, 0) for m in problem.models]
        s = sum(counts)
        total += (s * s - sum(c * c for c in counts)) // 2
    return total


def gpu_loads(problem: PlanProblem, assignment: Mapping[str, Mapping[int, int]]) -> list[Fraction]:
    """Exact sum_i r_ij / C_i for every GPU (1 = at its limit)."""
    loads = [Fraction(0)] * problem.num_gpus
    for m in problem.models:
        for j, r in assignment.get(m.name, {}).items():
            loads[j] += Fraction(r, m.limit)
    return loads


def check_assignment(problem: PlanProblem, assignment: Mapping[str, Mapping[int, int]]) -> list[str]:
    """Violations of (1), host placement and (2), as readable strings; empty when valid."""
    problems: list[str] = []
    for m in problem.models:
        row = assignment.get(m.name, {})
        for j, r in row.items():
            if r < 0:
                problems.append(f"{m.name}: negative count {r} on GPU {j}")
            if r and j not in m.gpus:
                problems.append(f"{m.name}: {r} robots on GPU {j}, which does not host it")
        if sum(row.values()) != m.robots:
            problems.append(f"{m.name}: {sum(row.values())} robots assigned, population is {m.robots}")
    for j, load in enumerate(gpu_loads(problem, assignment)):
        if load > 1:
            problems.append(f"GPU {j}: load {float(load):.2f} of its capacity")
    return problems


def _finish(
    problem: PlanProblem,
    strategy: str,
    assignment: dict[str, dict[int, int]],
    start: float,
    *,
    optimal: bool = False,
    status: str | None = None,
    best_bound: float | None = None,
) -> PlanResult:
    clean = {m.name: {j: r for j, r in sorted(assignment.get(m.name, {}).items()) if r} for m in problem.models}
    loads = gpu_loads(problem, clean)
    within = all(load <= 1 for load in loads)
    diagnosis = None
    if not within:
        over = [f"GPU {j} at {float(load):.2f}" for j, load in enumerate(loads) if load > 1]
        diagnosis = f"{strategy} assignment exceeds GPU limits: " + ", ".join(over)
    return PlanResult(
        strategy=strategy,
        assignment=clean,
        objective=objective_value(problem, clean),
        feasible=within,
        optimal=optimal,
        status=status or ("feasible" if within else "overloaded"),
        solve_time_s=time.perf_counter() - start,
        diagnosis=diagnosis,
        best_bound=best_bound,
        gpu_load=loads,
    )


def _order_by_demand(problem: PlanProblem) -> list[ModelDemand]:
    # Largest consumers first, so they claim whole GPUs before small models fragment them.
    return sorted(problem.models, key=lambda m: (-m.gpu_equivalents, -m.robots, m.name))


# --------------------------------------------------------------------------- SMG / EPS


def solve_smg(problem: PlanProblem) -> PlanResult:
    """Single model per GPU: every model's robots all go to one of its hosting GPUs.

    The GPU is the hosting GPU with the least load so far (ties: lowest index), models
    taken by decreasing N_i/C_i. With at least as many GPUs as models and full
    placement each model gets its own GPU; with more models than GPUs, GPUs end up
    shared (and possibly overloaded) -- the strategy never splits a model.
    """
    start = time.perf_counter()
    load = [Fraction(0)] * problem.num_gpus
    assignment: dict[str, dict[int, int]] = {}
    for m in _order_by_demand(problem):
        if m.robots == 0:
            continue
        j = min(m.gpus, key=lambda g: (load[g], g))
        assignment[m.name] = {j: m.robots}
        load[j] += m.gpu_equivalents
    return _finish(problem, "smg", assignment, start)


def solve_eps(problem: PlanProblem) -> PlanResult:
    """Even population split: N_i spread over the hosting GPUs as evenly as integers allow.

    Each hosting GPU gets floor(N_i / h) robots; the N_i mod h leftover robots go one
    each to the hosting GPUs that are least loaded at that point (ties: lowest index).
    """
    start = time.perf_counter()
    load = [Fraction(0)] * problem.num_gpus
    assignment: dict[str, dict[int, int]] = {}
    for m in _order_by_demand(problem):
        if m.robots == 0:
            continue
        base, extra = divmod(m.robots, len(m.gpus))
        row = {j: base for j in m.gpus}
        for j in m.gpus:
            load[j] += Fraction(base, m.limit)
        for j in sorted(m.gpus, key=lambda g: (load[g], g))[:extra]:
            row[j] += 1
            load[j] += Fraction(1, m.limit)
        assignment[m.name] = row
    return _finish(problem, "eps", assignment, start)


# --------------------------------------------------------------------------- feasibility analysis


def _max_flow(n: int, edges: list[tuple[int, int, int]], s: int, t: int) -> tuple[int, list[bool], dict[tuple[int, int], int]]:
    """Edmonds-Karp on a tiny graph; returns (flow value, source side of a min cut, edge flows)."""
    cap: dict[tuple[int, int], int] = {}
    adj: list[set[int]] = [set() for _ in range(n)]
    for u, v, c in edges:
        cap[(u, v)] = cap.get((u, v), 0) + c
        cap.setdefault((v, u), 0)
        adj[u].add(v)
        adj[v].add(u)
    orig = dict(cap)
    flow = 0
    while True:
        parent = [-1] * n
        parent[s] = s
        q = deque([s])
        while q and parent[t] == -1:
            u = q.popleft()
            for v in adj[u]:
                if parent[v] == -1 and cap[(u, v)] > 0:
                    parent[v] = u
                    q.append(v)
        if parent[t] == -1:
            reach = [p != -1 for p in parent]
            used = {e: orig[e] - cap[e] for e in orig if orig[e] > 0}
            return flow, reach, used
        push, v = None, t
        while v != s:
            u = parent[v]
            push = cap[(u, v)] if push is None else min(push, cap[(u, v)])
            v = u
        v = t
        while v != s:
            u = parent[v]
            cap[(u, v)] -= push
            cap[(v, u)] += push
            v = u
        flow += push


def _fmt(x: Fraction) -> str:
    return f"{float(x):.2f}"


def _gpu_list(gpus: Iterable[int]) -> str:
    gs = sorted(gpus)
    return ("GPU " if len(gs) == 1 else "GPUs ") + ", ".join(map(str, gs))


def diagnose_capacity(problem: PlanProblem) -> str | None:
    """Explain why constraints (1)+(2) cannot hold, or None when the fractional relaxation fits.

    Treats capacity as divisible: model i must place N_i/C_i GPU-equivalents on its
    hosts, each GPU offers 1. A max-flow/min-cut over models -> hosting GPUs finds the
    set of models whose combined demand exceeds what their hosting GPUs offer (Hall's
    condition); any such set makes the integer program infeasible too.
    """
    models = [m for m in problem.models if m.robots > 0]
    if not models:
        return None
    scale = math.lcm(*(m.limit for m in models))  # exact integer capacities
    M, G = len(models), problem.num_gpus
    s, t = M + G, M + G + 1
    big = scale * (G + 1)
    edges = [(s, i, m.robots * (scale // m.limit)) for i, m in enumerate(models)]
    edges += [(i, M + j, big) for i, m in enumerate(models) for j in m.gpus]
    edges += [(M + j, t, scale) for j in range(G)]
    flow, reach, used = _max_flow(M + G + 2, edges, s, t)
    demand = sum(m.robots * (scale // m.limit) for m in models)
    if flow >= demand:
        return None

    # Source side of the min cut: models whose demand cannot all be routed. Split it into
    # groups that share GPUs so each message names one bottleneck.
    short = [i for i in range(M) if reach[i]]
    groups: list[list[int]] = []
    for i in short:
        hosts = set(models[i].gpus)
        merged = [g for g in groups if any(hosts & set(models[k].gpus) for k in g)]
        new = [i] + [k for g in merged for k in g]
        groups = [g for g in groups if g not in merged] + [new]
    gpu_used = [Fraction(used.get((M + j, t), 0), scale) for j in range(G)]

    lines = ["infeasible: the GPUs hosting these models cannot serve their robots within the limits."]
    for g in sorted(groups, key=lambda g: min(g)):
        ms = [models[i] for i in sorted(g)]
        hosts = sorted({j for m in ms for j in m.gpus})
        need = sum((m.gpu_equivalents for m in ms), Fraction(0))
        have = Fraction(len(hosts))
        detail = "; ".join(f"{m.name}: {m.robots} robots / limit {m.limit} = {_fmt(m.gpu_equivalents)}" for m in ms)
        names = ", ".join(m.name for m in ms)
        lines.append(
            f"  - {'model' if len(ms) == 1 else 'models'} {names} need {_fmt(need)} GPU-equivalents "
            f"({detail}) but {'is' if len(ms) == 1 else 'are'} hosted only on {_gpu_list(hosts)} "
            f"offering {_fmt(have)}; short by {_fmt(need - have)}."
        )
        for m in ms:
            if m.gpu_equivalents > len(m.gpus):
                lines.append(
                    f"    {m.name} alone needs {_fmt(m.gpu_equivalents)} but its {_gpu_list(m.gpus)} "
                    f"offer only {len(m.gpus)}.00."
                )
        spare = [j for j in range(G) if j not in hosts and gpu_used[j] < 1]
        add = math.ceil(need - have)
        hint = f"    Add at least {add} GPU{'s' if add > 1 else ''} hosting {names}"
        if spare:
            free = sum((1 - gpu_used[j] for j in spare), Fraction(0))
            hint += f", or also place {'it' if len(ms) == 1 else 'them'} on {_gpu_list(spare)} ({_fmt(free)} GPU-equivalents spare)"
        hint += ", or lower the robot populations."
        lines.append(hint)
    return "\n".join(lines)


def _fragmentation_message(problem: PlanProblem) -> str:
    need = sum((m.gpu_equivalents for m in problem.models), Fraction(0))
    per_model = "; ".join(f"{m.name}: {_fmt(m.gpu_equivalents)} on {_gpu_list(m.gpus)}" for m in problem.models if m.robots)
    return (
        "infeasible: the demand fits in GPU-equivalents "
        f"(total {_fmt(need)} of {problem.num_gpus}) but no split into whole robots does: "
        "mixing models with different limits on a GPU leaves unusable fractions of capacity "
        f"({per_model}). Add a GPU, place models with the same limit together, or lower a population."
    )


# --------------------------------------------------------------------------- integer program


def _greedy(problem: PlanProblem) -> dict[str, dict[int, int]] | None:
    """Quick concentrated assignment used as a CP-SAT hint; None if it gets stuck.

    Biggest models first; each fills the hosting GPU with the most room for it, so
    models sit whole on GPUs while they fit and split only across full GPUs.
    """
    load = [Fraction(0)] * problem.num_gpus
    out: dict[str, dict[int, int]] = {}
    for m in _order_by_demand(problem):
        left, row = m.robots, {}
        while left > 0:
            room = {j: math.floor((1 - load[j]) * m.limit) for j in m.gpus if j not in row}
            if not room or max(room.values()) <= 0:
                return None
            # Prefer a GPU that takes the rest whole with the least slack, else the roomiest.
            fits = [j for j, c in room.items() if c >= left]
            j = min(fits, key=lambda g: (room[g], g)) if fits else max(room, key=lambda g: (room[g], -g))
            take = min(left, room[j])
            row[j] = take
            load[j] += Fraction(take, m.limit)
            left -= take
        out[m.name] = row
    return out


# Up to this bound a square is a table lookup, which CP-SAT linearizes tightly; measured
# clearly faster than multiplication constraints on the bench instances (limits 2-12).
_SQUARE_TABLE_MAX = 256


def _add_square(mdl: cp_model.CpModel, x: cp_model.IntVar, ub: int, target: cp_model.IntVar) -> None:
    if ub <= _SQUARE_TABLE_MAX:
        mdl.add_element(x, [v * v for v in range(ub + 1)], target)
    else:
        mdl.add_multiplication_equality(target, [x, x])


def solve_ip(
    problem: PlanProblem,
    time_limit_s: float = DEFAULT_TIME_LIMIT_S,
    num_workers: int | None = None,
    random_seed: int = 0,
) -> PlanResult:
    """Solve (1)-(3) with CP-SAT. ``optimal`` tells whether the objective was proven minimal."""
    start = time.perf_counter()
    # CP-SAT does not refuse a negative or NaN time limit up front: it answers MODEL_INVALID,
    # which would read as "no assignment found in time".
    if not time_limit_s > 0:
        raise PlanInputError("time_limit_s", f"expected a positive number of seconds, got {time_limit_s!r}")
    diag = diagnose_capacity(problem)
    if diag is not None:
        return PlanResult("ip", {}, None, False, False, "infeasible", time.perf_counter() - start, diag)

    G = problem.num_gpus
    mdl = cp_model.CpModel()
    r: dict[tuple[int, int], cp_model.IntVar] = {}
    for i, m in enumerate(problem.models):
        if m.robots == 0:
            continue
        # r_ij <= C_i is implied by (2); stating it keeps domains small and the scaled
        # capacity coefficients times bounds within int64.
        ub = min(m.robots, m.limit)
        # Constraint (1) sums one such variable per host: past int64 OR-Tools raises a TypeError
        # (a bound itself too large) or CP-SAT refuses the model as MODEL_INVALID.
        if ub * len(m.gpus) > _MAX_SCALED_ACTIVITY:
            raise PlanInputError(
                f"models.{m.name}",
                f"{m.robots} robots with limit {m.limit} on {len(m.gpus)} GPUs are too large for the integer "
                "program (its sums would overflow int64)",
            )
        for j in m.gpus:
            r[i, j] = mdl.new_int_var(0, ub, f"r_{i}_{j}")
        mdl.add(sum(r[i, j] for j in m.gpus) == m.robots)

    twice_obj: list = []
    obj_bound = 0  # largest |2 x objective| the terms below can reach; CP-SAT refuses one past int64
    hosted: dict[int, list[int]] = {j: [i for (i, jj) in r if jj == j] for j in range(G)}
    for j, models_j in hosted.items():
        if not models_j:
            continue
        limits = [problem.models[i].limit for i in models_j]
        # Exact form of sum_i r_ij / C_i <= 1: multiply through by P = lcm(C_i on GPU j).
        scale = math.lcm(*limits)
        if scale * len(models_j) > _MAX_SCALED_ACTIVITY:
            raise PlanInputError(
                "models",
                f"robot limits of the models on GPU {j} ({sorted(set(limits))}) have a least common "
                "multiple too large for an exact integer capacity constraint",
            )
        mdl.add(sum((scale // problem.models[i].limit) * r[i, j] for i in models_j) <= scale)
        if len(models_j) < 2:
            continue  # a GPU with one model adds nothing to (3)
        # sum_{i<k} r_ij r_kj = (L_j^2 - sum_i r_ij^2) / 2 with L_j = sum_i r_ij: one square
        # per variable plus one per GPU instead of one product per model pair.
        # L_j is at most the sum of its terms' bounds: with a large C_i but few robots the
        # squares stay small, where max(C_i)^2 alone would overflow CP-SAT's int64 domains.
        ubs = [min(problem.models[i].robots, problem.models[i].limit) for i in models_j]
        max_load = min(max(limits), sum(ubs))
        obj_bound += max_load * max_load + sum(ub * ub for ub in ubs)
        if obj_bound > _MAX_SCALED_ACTIVITY:
            raise PlanInputError(
                "models",
                f"robot populations and limits of the models on GPU {j} are too large for the integer "
                "program's objective (squared robot counts overflow int64)",
            )
        load = mdl.new_int_var(0, max_load, f"L_{j}")
        mdl.add(load == sum(r[i, j] for i in models_j))
        load_sq = mdl.new_int_var(0, max_load * max_load, f"L2_{j}")
        _add_square(mdl, load, max_load, load_sq)
        twice_obj.append(load_sq)
        for i, ub in zip(models_j, ubs):
            sq = mdl.new_int_var(0, ub * ub, f"s_{i}_{j}")
            _add_square(mdl, r[i, j], ub, sq)
            twice_obj.append(-sq)

    # GPUs hosting the same models are interchangeable: order them by the first model's
    # count so the solver does not revisit permutations of one assignment.
    groups: dict[tuple[int, ...], list[int]] = {}
    for j, models_j in hosted.items():
        if models_j:
            groups.setdefault(tuple(sorted(models_j)), []).append(j)
    for key, gpus in groups.items():
        first = key[0]
        for a, b in zip(gpus, gpus[1:]):
            mdl.add(r[first, a] >= r[first, b])

    hint = _greedy(problem)
    if hint is not None:
        for key, gpus in groups.items():
            # Permute the hint's columns within each group so it satisfies the ordering above.
            cols = sorted(
                gpus,
                key=lambda g: tuple(-hint.get(problem.models[i].name, {}).get(g, 0) for i in key),
            )
            for i in key:
                row = hint.setdefault(problem.models[i].name, {})
                vals = [row.get(g, 0) for g in cols]
                for g, v in zip(gpus, vals):
                    row[g] = v
        for (i, j), v in r.items():
            mdl.add_hint(v, hint.get(problem.models[i].name, {}).get(j, 0))

    mdl.minimize(sum(twice_obj))

    solver = cp_model.CpSolver()
    solver.parameters.max_time_in_seconds = float(time_limit_s)
    solver.parameters.num_workers = num_workers or min(8, os.cpu_count() or 1)
    solver.parameters.random_seed = random_seed
    status = solver.solve(mdl)
    name = solver.status_name(status)
    log.debug("CP-SAT %s in %.3fs: %s", name, solver.wall_time, solver.response_stats())

    if status in (cp_model.OPTIMAL, cp_model.FEASIBLE):
        assignment: dict[str, dict[int, int]] = {m.name: {} for m in problem.models}
        for (i, j), v in r.items():
            assignment[problem.models[i].name][j] = int(solver.value(v))
        optimal = status == cp_model.OPTIMAL
        res = _finish(
            problem,
            "ip",
            assignment,
            start,
            optimal=optimal,
            status="optimal" if optimal else "feasible",
            best_bound=solver.best_objective_bound / 2,
        )
        if not res.feasible:  # would be a formulation bug; never hand out an overload silently
            raise AssertionError(f"CP-SAT returned an overloaded assignment: {res.diagnosis}")
        return res
    if status == cp_model.MODEL_INVALID:
        # A formulation the checks above did not foresee; not a time-out, so say what CP-SAT refused.
        raise PlanInputError("models", f"CP-SAT refused the integer program (int64 bounds?): {mdl.validate()}")
    if status == cp_model.INFEASIBLE:
        return PlanResult("ip", {}, None, False, False, "infeasible", time.perf_counter() - start, _fragmentation_message(problem))
    msg = (
        f"no feasible assignment found within the {time_limit_s:g}s time limit (CP-SAT status {name}); "
        "the problem may still be feasible: raise the time limit."
    )
    return PlanResult("ip", {}, None, False, False, "unknown", time.perf_counter() - start, msg)


def solve(
    problem: PlanProblem,
    strategy: str = "ip",
    time_limit_s: float = DEFAULT_TIME_LIMIT_S,
    num_workers: int | None = None,
) -> PlanResult:
    """Assign robots to GPUs with ``strategy`` in ``ip`` | ``smg`` | ``eps``."""
    if strategy == "ip":
        return solve_ip(problem, time_limit_s=time_limit_s, num_workers=num_workers)
    if strategy == "smg":
        return solve_smg(problem)
    if strategy == "eps":
        return solve_eps(problem)
    raise ValueError(f"unknown strategy {strategy!r}; expected one of {', '.join(STRATEGIES)}")


def make_problem(num_gpus: int, models: Sequence[tuple[str, int, int, Sequence[int] | None]]) -> PlanProblem:
    """Convenience constructor: (name, limit, robots, hosting GPUs or None for all)."""
    return PlanProblem(
        num_gpus,
        tuple(
            ModelDemand(name, limit, robots, tuple(range(num_gpus)) if gpus is None else tuple(gpus))
            for name, limit, robots, gpus in models
        ),
    )
