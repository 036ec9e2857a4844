"""Traffic controller: how many robots of each model every GPU serves (paper §4.2).

Given G GPUs and models i with robot limit C_i (the most robots of model i one GPU
sustains at the target SLO), population N_i and the set of GPUs hosting it, choose
integers r_ij (robots of model i served by GPU j, 0 where j does not host i) with

    (1) sum_j r_ij = N_i                 every model's robots are all served
    (2) sum_i r_ij / C_i <= 1            no GPU is pushed past its limit
    (3) minimize sum_j sum_{i<k} r_ij * r_kj

The objective is zero exactly when every GPU serves one model, so minimizing it keeps
each model's traffic concentrated in few FIFO queues (large batches) while (2) splits a
model over more GPUs only as far as the limits force. Among plans with the same (3) the
integer program takes one with the fewest (model, GPU) pairs: (3) is zero for a model
alone on 4 GPUs with 1 robot each, and that plan batches no better than the even split.

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
import time
from collections import deque
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Callable, Iterable, Mapping, Sequence

from ortools.graph.python import max_flow
from ortools.sat.python import cp_model

log = logging.getLogger(__name__)

STRATEGIES = ("ip", "smg", "eps")
# Stays under the 10 s budget for 32 models x 16 GPUs including model building; the result
# says whether optimality was proven within it.
DEFAULT_TIME_LIMIT_S = 8.0

# Most GPUs one plan may span. A planning file states the count as a plain number: without a
# bound `gpus: 100000000` allocated host lists until MemoryError. 4096 is far above any cluster
# one control plane drives, and its model still builds in seconds.
MAX_GPUS = 4096

# Share of the time limit that CP-SAT gets as deterministic time. Measured on the bench's 2-core
# machine a deterministic second takes 2-2.5 wall seconds; a quarter keeps the deterministic limit the
# one that ends a time-out there (so it ends the same way every run), and the 32 x 16 bench instances
# reach the same objectives as with the whole limit.
_DETERMINISTIC_SHARE = 0.25

# CP-SAT is not started when the integer program has more (model, GPU) pairs than this per second
# of the time limit: on the bench's 2-core machine its presolve took 6 s for 16k pairs and 11 s for 32k
# with 5 s left, most of it in steps that do not check the limit. The greedy plan is returned instead.
_MAX_IP_VARS_PER_S = 2000
# Above this many pairs CP-SAT's symmetry detection is off (see solve_ip).
_SYMMETRY_MAX_VARS = 1024

# Share of the seconds left that a search for any plan gets when the greedy plan is stuck (see _first_plan).
_FIRST_PLAN_SHARE = 0.25

# Below this many seconds left of the time limit CP-SAT is not started: it could not even
# finish presolve, and the greedy plan (if any) is what it would return anyway.
_MIN_SOLVE_S = 0.05

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
    empty when no assignment exists (IP infeasible, or timed out with neither a CP-SAT
    solution nor a greedy plan).
    ``objective`` is the value of (3) for the assignment, None without one.
    ``feasible`` means the assignment exists and respects every GPU limit (2).
    ``optimal`` is True only when it is proven that no plan has a lower objective (3),
    whichever of CP-SAT's and the greedy plan was returned; ``best_bound`` is the proven
    lower bound on (3) behind that: a non-negative integer for ``ip`` (0 when CP-SAT did not
    run or proved nothing more), None for ``smg`` and ``eps``.
    ``source`` says where an ``ip`` assignment came from: ``cp-sat``, or ``greedy`` when the
    quick greedy plan was at least as good as anything CP-SAT found within the time limit.
    """

    strategy: str
    assignment: dict[str, dict[int, int]]
    objective: int | None
    feasible: bool
    optimal: bool
    status: str  # optimal | feasible | overloaded | infeasible | unknown
    solve_time_s: float
    diagnosis: str | None = None
    best_bound: int | None = None  # proven lower bound on the objective (3)
    gpu_load: list[Fraction] = field(default_factory=list)  # sum_i r_ij / C_i per GPU
    source: str | None = None  # ip only: "cp-sat" or "greedy"

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


def check_num_gpus(num_gpus: object, path: str = "gpus") -> int:
    """``num_gpus`` if it is a GPU count the planner takes (1..MAX_GPUS), else PlanInputError at ``path``.

    Callers that build per-GPU lists from a count read from a file check it with this first."""
    if not _is_int(num_gpus) or num_gpus < 1:
        raise PlanInputError(path, f"expected a positive integer, got {num_gpus!r}")
    if num_gpus > MAX_GPUS:
        raise PlanInputError(path, f"at most {MAX_GPUS} GPUs can be planned, got {num_gpus}")
    return num_gpus


def validate_problem(problem: PlanProblem) -> None:
    """Raise PlanInputError (with a field path) for inputs the solver cannot take."""
    check_num_gpus(problem.num_gpus)
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


def pairs_used(problem: PlanProblem, assignment: Mapping[str, Mapping[int, int]]) -> int:
    """Number of (model, GPU) pairs with at least one robot: the integer program's tie-break after (3)."""
    return sum(1 for m in problem.models for r in assignment.get(m.name, {}).values() if r)


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
    best_bound: int | None = None,
    source: str | None = None,
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
        source=source,
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


def _max_flow_fast(
    n: int, edges: list[tuple[int, int, int]], s: int, t: int
) -> tuple[int, list[bool], dict[tuple[int, int], int]] | None:
    """_max_flow's answer from OR-Tools' C++ max flow; None where a capacity does not fit its int64.

    Edmonds-Karp in Python took a minute on 4096 GPUs hosting different model sets (one augmenting
    path per GPU, each a search of the whole graph), far past any planning time limit."""
    source_total = sum(c for u, _, c in edges if u == s)
    if source_total >= _MAX_SCALED_ACTIVITY or any(c >= _MAX_SCALED_ACTIVITY for _, _, c in edges):
        return None
    flow = max_flow.SimpleMaxFlow()
    arcs = [flow.add_arc_with_capacity(u, v, c) for u, v, c in edges]
    if flow.solve(s, t) != flow.OPTIMAL:
        return None
    reach = [False] * n
    for v in flow.get_source_side_min_cut():
        reach[v] = True
    used: dict[tuple[int, int], int] = {}
    for (u, v, _), a in zip(edges, arcs):
        used[(u, v)] = used.get((u, v), 0) + flow.flow(a)
    return flow.optimal_flow(), reach, used


def _fmt(x: Fraction) -> str:
    """Two decimals, exactly: through a float, a population of 10^23 read 24999999999999997902848.00 beside the
    exact "Add at least 24999999999999999999998 GPUs"."""
    cents = math.floor(abs(x) * 100 + Fraction(1, 2))  # half away from zero
    return f"{'-' if x < 0 and cents else ''}{cents // 100}.{cents % 100:02d}"


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
    # GPUs hosting the same set of these models are interchangeable here, so each such set is one
    # node offering its GPUs' total capacity: the same max flow and cut on a graph that stays small
    # (4096 GPUs hosting every model are one node; one node per GPU took 48 s to cut in Python).
    hosting: list[list[int]] = [[] for _ in range(G)]
    for i, m in enumerate(models):
        for j in m.gpus:
            hosting[j].append(i)
    by_set: dict[tuple[int, ...], list[int]] = {}
    for j in range(G):
        if hosting[j]:
            by_set.setdefault(tuple(hosting[j]), []).append(j)
    columns = list(by_set.items())
    K = len(columns)
    s, t = M + K, M + K + 1

    def network(scale: int, demand: Callable[[ModelDemand], int]) -> list[tuple[int, int, int]]:
        """Source -> model (its demand) -> host set -> sink (``scale`` per GPU); the first M edges are the demands."""
        edges = [(s, i, demand(m)) for i, m in enumerate(models)]
        edges += [(i, M + k, scale * (G + 1)) for k, (key, _) in enumerate(columns) for i in key]
        return edges + [(M + k, t, scale * len(gpus)) for k, (_, gpus) in enumerate(columns)]

    def relaxation(edges: list[tuple[int, int, int]], exact: bool = False):
        """(flow, source side of a min cut, edge flows, total demand); None where OR-Tools' int64 overflows and
        not ``exact`` (the Python max flow takes any size, slowly)."""
        found = _max_flow_fast(M + K + 2, edges, s, t) or (_max_flow(M + K + 2, edges, s, t) if exact else None)
        return None if found is None else (*found, sum(c for _, _, c in edges[:M]))

    exact = network(scale, lambda m: m.robots * (scale // m.limit))
    slack = Fraction(0)  # how far below full a GPU that is full may read (the bracket's rounding)
    solved = relaxation(exact)
    if solved is None:
        # The lcm of many distinct limits overflows int64, and the exact max flow in Python took 10-24 s on 4096 GPUs
        # against a 1 s limit, the control plane blocked meanwhile. A power-of-two scale brackets the exact answer:
        # with demands rounded up, a flow that carries them all proves the relaxation fits; with demands rounded
        # down, one that cannot has a cut whose models need more than their GPUs offer, exactly. Only a problem
        # between the two (within about 2^-40 of a GPU) is left to the exact flow.
        room = _MAX_SCALED_ACTIVITY // (G + 1 + sum(math.ceil(m.gpu_equivalents) + 1 for m in models))
        if room >= 2:
            approx = 1 << (room.bit_length() - 1)
            up = relaxation(network(approx, lambda m: -(-m.robots * approx // m.limit)))
            if up is not None and up[0] >= up[3]:
                return None
            down = relaxation(network(approx, lambda m: m.robots * approx // m.limit))
            if down is not None and down[0] < down[3]:
                # Each model's demand lost less than one unit to the rounding, so a host set's flow (filled into its
                # GPUs in index order below) reads at most M units short.
                solved, scale, slack = down, approx, Fraction(M, approx)
    if solved is None:
        solved = relaxation(exact, exact=True)
    flow, reach, used, demand = solved
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
    # Spread each set's flow over its GPUs, filling them in index order.
    gpu_used = [Fraction(0)] * G
    for k, (_, gpus) in enumerate(columns):
        left = used.get((M + k, t), 0)
        for j in gpus:
            take = min(left, scale)
            gpu_used[j] = Fraction(take, scale)
            left -= take

    lines = ["infeasible: the GPUs hosting these models cannot serve their robots within the limits."]
    for g in sorted(groups, key=lambda g: min(g)):
        ms = [models[i] for i in sorted(g)]
        hosts = sorted({j for m in ms for j in m.gpus})
        need = sum((m.gpu_equivalents for m in ms), Fraction(0))
        have = Fraction(len(hosts))
        detail = "; ".join(f"{m.name}: {m.robots} robots / limit {m.limit} = {_fmt(m.gpu_equivalents)}" for m in ms)
        names = ", ".join(m.name for m in ms)
        lines.append(
            f"  - {'model' if len(ms) == 1 else 'models'} {names} {'needs' if len(ms) == 1 else 'need'} "
            f"{_fmt(need)} GPU-equivalents "
            f"({detail}) but {'is' if len(ms) == 1 else 'are'} hosted only on {_gpu_list(hosts)} "
            f"offering {_fmt(have)}; short by {_fmt(need - have)}."
        )
        for m in ms:
            if m.gpu_equivalents > len(m.gpus):
                lines.append(
                    f"    {m.name} alone needs {_fmt(m.gpu_equivalents)} but its {_gpu_list(m.gpus)} "
                    f"offer only {len(m.gpus)}.00."
                )
        spare = [j for j in range(G) if j not in hosts and gpu_used[j] < 1 - slack]
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


def plan_key(problem: PlanProblem, assignment: Mapping[str, Mapping[int, int]]) -> tuple[int, int]:
    """What the integer program minimizes, in this order: objective (3), then (model, GPU) pairs used."""
    return objective_value(problem, assignment), pairs_used(problem, assignment)


def _greedy_pass(problem: PlanProblem, prefer_empty: bool) -> dict[str, dict[int, int]] | None:
    """One greedy pass (see _greedy); None where a model's robots do not fit its hosts' room left."""
    load: dict[int, Fraction] = {}  # GPUs given robots so far
    occupied: dict[int, int] = {}  # and how many
    out: dict[str, dict[int, int]] = {}
    order = _order_by_demand(problem)
    # Ties go to the GPUs fewest models still to come can use: by index alone, a model on every GPU filled GPU 0
    # first even where that was the only host of a model after it, and the pass got stuck on a plainly feasible
    # problem (with the integer program too large for the time limit, the control plane then split robots evenly,
    # over a GPU's limit).
    wanted: dict[int, int] = {}  # GPU -> models still to place that it hosts
    for m in order:
        if m.robots:
            for j in m.gpus:
                wanted[j] = wanted.get(j, 0) + 1
    for m in order:
        if m.robots:
            for j in m.gpus:
                wanted[j] -= 1
        left, row = m.robots, {}
        # A GPU's room for this model stays the same while the model is placed: only the GPUs it
        # takes change, and it never takes one twice. One sort per model, not a scan per robot batch.
        room = {j: math.floor((1 - load[j]) * m.limit) if j in load else m.limit for j in m.gpus}
        by_room = sorted((j for j in m.gpus if room[j] > 0),
                         key=lambda g: (-room[g], occupied.get(g, 0), wanted.get(g, 0), g))
        k = 0
        while left > 0 and k < len(by_room) and room[by_room[k]] < left:
            j = by_room[k]  # no host takes the rest whole: fill the roomiest
            row[j] = room[j]
            left -= room[j]
            k += 1
        if left > 0:
            if k == len(by_room):
                return None
            fits = [g for g in by_room[k:] if room[g] >= left]
            if prefer_empty:
                # The rest whole on the GPU with the fewest robots of other models (each adds `left`
                # to objective (3)), then the least slack.
                j = min(fits, key=lambda g: (occupied.get(g, 0), room[g], wanted.get(g, 0), g))
            else:
                # Best fit: the least slack, keeping roomy GPUs for the models still to come.
                j = min(fits, key=lambda g: (room[g], occupied.get(g, 0), wanted.get(g, 0), g))
            row[j] = left
        for j, c in row.items():
            load[j] = load.get(j, Fraction(0)) + Fraction(c, m.limit)
            occupied[j] = occupied.get(j, 0) + c
        out[m.name] = row
    return out


def _greedy(problem: PlanProblem) -> dict[str, dict[int, int]] | None:
    """Quick concentrated assignment: CP-SAT's starting point and the fallback plan; None if it gets stuck.

    Biggest models first. While no hosting GPU takes all of a model's remaining robots, the roomiest
    one is filled; the rest then goes whole to one GPU, so models sit whole on GPUs while they fit and
    split only across full GPUs. Two passes differ in that last choice (fewest robots of other models
    there, or best fit); the better valid plan by ``plan_key`` is returned. It never moves a robot
    once placed, so it can get stuck on problems that are feasible.
    """
    best, best_key = None, None
    for prefer_empty in (True, False):
        plan = _greedy_pass(problem, prefer_empty)
        if plan is None or check_assignment(problem, plan):
            continue
        key = plan_key(problem, plan)
        if best_key is None or key < best_key:
            best, best_key = plan, key
    return best


# Up to this bound a square is a table lookup, which CP-SAT linearizes tightly; measured
# clearly faster than multiplication constraints on the bench instances (limits 2-12).
_SQUARE_TABLE_MAX = 256
# CP-SAT reports the objective bound as a double: keep the weighted objective where doubles
# are exact integers, so the bound on (3) read back from it is exact.
_MAX_EXACT_OBJECTIVE = 2**53


def _add_square(mdl: cp_model.CpModel, x: cp_model.IntVar, ub: int, target: cp_model.IntVar) -> None:
    if ub <= _SQUARE_TABLE_MAX:
        mdl.add_element(x, [v * v for v in range(ub + 1)], target)
    else:
        mdl.add_multiplication_equality(target, [x, x])


@dataclass
class _IpModel:
    """The CP-SAT model of (1)-(3) and what reading its answer needs."""

    mdl: cp_model.CpModel
    r: dict[tuple[int, int], cp_model.IntVar]
    # CP-SAT minimizes weight * 2 * (3) + (pairs used); weight = pairs + 1 keeps the pair count
    # strictly below one unit of (3), so it only breaks ties. weight 1 and no pair term when the
    # weighted objective would pass _MAX_EXACT_OBJECTIVE.
    weight: int
    num_pairs: int
    with_pairs: bool
    # Auxiliary variables, kept to give CP-SAT a complete hint.
    used: dict[tuple[int, int], cp_model.IntVar] = field(default_factory=dict)
    loads: dict[int, tuple[cp_model.IntVar, cp_model.IntVar, list[int]]] = field(default_factory=dict)
    squares: dict[tuple[int, int], cp_model.IntVar] = field(default_factory=dict)
    groups: dict[tuple[int, ...], list[int]] = field(default_factory=dict)


class _OutOfTime(Exception):
    """The time limit passed while the model was being built."""


def _hosted(problem: PlanProblem) -> dict[int, list[int]]:
    """GPU -> indices (in model order) of the models with robots that it hosts: the r_ij that exist."""
    hosted: dict[int, list[int]] = {j: [] for j in range(problem.num_gpus)}
    for i, m in enumerate(problem.models):
        if m.robots:
            for j in m.gpus:
                hosted[j].append(i)
    return hosted


def _check_statable(problem: PlanProblem, hosted: Mapping[int, list[int]]) -> int:
    """Raise PlanInputError where the integer program cannot be stated in int64; else the largest
    |2 x objective (3)| its terms can reach (CP-SAT refuses an objective past int64).

    solve_ip returns the greedy plan where it has one, and refuses such inputs only without one (the
    control plane then splits evenly, see traffic.assign)."""
    for m in problem.models:
        # Constraint (1) sums one variable of bound min(N_i, C_i) per host: past int64 OR-Tools raises
        # a TypeError (a bound itself too large) or CP-SAT refuses the model as MODEL_INVALID.
        if m.robots and min(m.robots, m.limit) * len(m.gpus) > _MAX_SCALED_ACTIVITY:
            raise PlanInputError(
                f"models.{m.name}",
                f"{m.robots} robots with limit {m.limit} on {len(m.gpus)} GPUs are too large for the integer "
                "program (its sums would overflow int64)",
            )
    obj_bound = 0
    for j, models_j in hosted.items():
        if not models_j:
            continue
        limits = [problem.models[i].limit for i in models_j]
        # Constraint (2) is stated exactly, multiplied through by lcm(C_i on GPU j).
        if math.lcm(*limits) * len(models_j) > _MAX_SCALED_ACTIVITY:
            raise PlanInputError(
                "models",
                f"robot limits of the models on GPU {j} ({sorted(set(limits))}) have a least common "
                "multiple too large for an exact integer capacity constraint",
            )
        if len(models_j) < 2:
            continue
        ubs = [min(problem.models[i].robots, problem.models[i].limit) for i in models_j]
        max_load = min(max(limits), sum(ubs))
        obj_bound += max_load * max_load + sum(ub * ub for ub in ubs)
        if obj_bound > _MAX_SCALED_ACTIVITY:
            raise PlanInputError(
                "models",
                f"robot populations and limits of the models on GPU {j} are too large for the integer "
                "program's objective (squared robot counts overflow int64)",
            )
    return obj_bound


def _build_ip(problem: PlanProblem, hosted: Mapping[int, list[int]], obj_bound: int, deadline: float) -> _IpModel:
    """The CP-SAT model of a problem _check_statable passed; raises _OutOfTime past ``deadline``."""
    mdl = cp_model.CpModel()
    r: dict[tuple[int, int], cp_model.IntVar] = {}
    for i, m in enumerate(problem.models):
        if m.robots == 0:
            continue
        # r_ij <= C_i is implied by (2); stating it keeps domains small and the scaled
        # capacity coefficients times bounds within int64.
        ub = min(m.robots, m.limit)
        for j in m.gpus:
            r[i, j] = mdl.new_int_var(0, ub, f"r_{i}_{j}")
        mdl.add(cp_model.LinearExpr.sum([r[i, j] for j in m.gpus]) == m.robots)
        if time.perf_counter() > deadline:
            raise _OutOfTime

    twice_obj: list = []
    ip = _IpModel(mdl, r, 1, len(r), False)
    for j, models_j in hosted.items():
        if time.perf_counter() > deadline:
            raise _OutOfTime
        if not models_j:
            continue
        limits = [problem.models[i].limit for i in models_j]
        # Exact form of sum_i r_ij / C_i <= 1: multiply through by P = lcm(C_i on GPU j).
        scale = math.lcm(*limits)
        mdl.add(cp_model.LinearExpr.weighted_sum([r[i, j] for i in models_j],
                                                  [scale // problem.models[i].limit for i in models_j]) <= scale)
        if len(models_j) < 2:
            continue  # a GPU with one model adds nothing to (3)
        # sum_{i<k} r_ij r_kj = (L_j^2 - sum_i r_ij^2) / 2 with L_j = sum_i r_ij: one square
        # per variable plus one per GPU instead of one product per model pair.
        # L_j is at most the sum of its terms' bounds: with a large C_i but few robots the
        # squares stay small, where max(C_i)^2 alone would overflow CP-SAT's int64 domains.
        ubs = [min(problem.models[i].robots, problem.models[i].limit) for i in models_j]
        max_load = min(max(limits), sum(ubs))
        load = mdl.new_int_var(0, max_load, f"L_{j}")
        mdl.add(load == cp_model.LinearExpr.sum([r[i, j] for i in models_j]))
        load_sq = mdl.new_int_var(0, max_load * max_load, f"L2_{j}")
        _add_square(mdl, load, max_load, load_sq)
        ip.loads[j] = (load, load_sq, models_j)
        twice_obj.append(load_sq)
        for i, ub in zip(models_j, ubs):
            sq = mdl.new_int_var(0, ub * ub, f"s_{i}_{j}")
            _add_square(mdl, r[i, j], ub, sq)
            ip.squares[i, j] = sq
            twice_obj.append(-sq)

    # GPUs hosting the same models are interchangeable: order them by the first model's
    # count so the solver does not revisit permutations of one assignment.
    for j, models_j in hosted.items():
        if models_j:
            ip.groups.setdefault(tuple(sorted(models_j)), []).append(j)
    for key, gpus in ip.groups.items():
        first = key[0]
        for a, b in zip(gpus, gpus[1:]):
            mdl.add(r[first, a] >= r[first, b])

    # Tie-break below (3): fewest (model, GPU) pairs, i.e. each model on as few GPUs as it can.
    # (3) alone is indifferent between a lone model's robots on one GPU or spread over four.
    ip.weight = ip.num_pairs + 1
    ip.with_pairs = obj_bound * ip.weight + ip.num_pairs <= _MAX_EXACT_OBJECTIVE
    if not ip.with_pairs:
        ip.weight = 1
        log.debug("objective too large for the pair-count tie-break; minimizing (3) alone")
        mdl.minimize(cp_model.LinearExpr.sum(twice_obj))
        return ip
    for (i, j), v in r.items():
        if time.perf_counter() > deadline:
            raise _OutOfTime
        u = mdl.new_bool_var(f"u_{i}_{j}")
        mdl.add(v >= 1).only_enforce_if(u)
        mdl.add(v == 0).only_enforce_if(~u)
        ip.used[i, j] = u
    for i, m in enumerate(problem.models):
        if m.robots:
            # Redundant: model i needs ceil(N_i / C_i) GPUs at least. Gives the pair term a lower bound from the start.
            mdl.add(cp_model.LinearExpr.sum([ip.used[i, j] for j in m.gpus]) >= -(-m.robots // m.limit))
    mdl.minimize(ip.weight * cp_model.LinearExpr.sum(twice_obj) + cp_model.LinearExpr.sum(list(ip.used.values())))
    return ip


def _add_hint(problem: PlanProblem, ip: _IpModel, plan: Mapping[str, Mapping[int, int]]) -> None:
    """Hint every variable (auxiliaries too) from ``plan``: CP-SAT then starts from a complete solution."""
    hint = {m.name: dict(plan.get(m.name, {})) for m in problem.models}
    for key, gpus in ip.groups.items():
        # Permute the plan's columns within each group so it satisfies the ordering constraints.
        cols = sorted(gpus, key=lambda g: tuple(-hint[problem.models[i].name].get(g, 0) for i in key))
        for i in key:
            row = hint[problem.models[i].name]
            vals = [row.get(g, 0) for g in cols]
            for g, v in zip(gpus, vals):
                row[g] = v
    value = {(i, j): hint[problem.models[i].name].get(j, 0) for (i, j) in ip.r}
    for ij, v in ip.r.items():
        ip.mdl.add_hint(v, value[ij])
    for ij, u in ip.used.items():
        ip.mdl.add_hint(u, value[ij] > 0)
    for j, (load, load_sq, models_j) in ip.loads.items():
        total = sum(value[i, j] for i in models_j)
        ip.mdl.add_hint(load, total)
        ip.mdl.add_hint(load_sq, total * total)
    for ij, sq in ip.squares.items():
        ip.mdl.add_hint(sq, value[ij] * value[ij])


def _bound_on_objective(ip: _IpModel, bound: float) -> int:
    """Proven lower bound on objective (3) from CP-SAT's bound on its weighted objective, never below 0.

    CP-SAT's bound can be negative (the squares it subtracts), and is a double; (3) is a count of robot
    pairs, so the bound reported is max(0, ceil(.)) of the real objective."""
    if not math.isfinite(bound):
        return 0
    # weighted = weight * twice + pairs with 0 <= pairs <= num_pairs, so twice >= (bound - num_pairs) / weight.
    # The weighted objective is an integer and CP-SAT's bound a double a rounding off it (20.000000000000004
    # for 20): ceil of that, one too high, had called a plan better than the true optimum's bound.
    b = math.ceil(bound - max(1e-6, 1e-12 * abs(bound)))
    twice = -((ip.num_pairs - b) // ip.weight) if ip.with_pairs else b  # ceil((b - num_pairs) / weight)
    return max(0, -(-twice // 2))


def _cp_sat_parameters(solver: cp_model.CpSolver, seconds: float, work: float, num_workers: int | None,
                       random_seed: int) -> None:
    """At most ``seconds`` of wall clock and ``work`` of CP-SAT's deterministic time."""
    p = solver.parameters
    # One worker follows one search path for a given model and seed; several race (CP-SAT's portfolio)
    # and returned a different optimal plan from run to run, so the control plane re-pinned about half
    # the robots on every re-solve of an unchanged cluster. On the bench instances (2 cores) one worker
    # reaches the same objectives; num_workers > 1 trades that determinism for parallel speed.
    p.num_workers = num_workers or 1
    p.random_seed = random_seed
    # The deterministic limit (CP-SAT's work count, about seconds on its reference machine) ends a
    # time-out at the same point on every run, so the caller derives it from its inputs alone, never from
    # the wall clock left; the wall-clock limit stays the hard cap.
    p.max_deterministic_time = work
    p.max_time_in_seconds = seconds


def _min_pairs(problem: PlanProblem) -> int:
    """Fewest (model, GPU) pairs any plan can use: model i needs ceil(N_i / C_i) GPUs, as r_ij <= C_i."""
    return sum(-(-m.robots // m.limit) for m in problem.models)


def solve_ip(
    problem: PlanProblem,
    time_limit_s: float = DEFAULT_TIME_LIMIT_S,
    num_workers: int | None = None,
    random_seed: int = 0,
) -> PlanResult:
    """Solve (1)-(3) within ``time_limit_s`` seconds, model building included.

    A greedy plan is made first (milliseconds). CP-SAT starts from it and gets what is left of the
    time limit; the better of its best plan and the greedy one (by ``plan_key``) is returned, so a
    time-out still returns the greedy plan when CP-SAT found nothing better (``source`` says which).
    ``optimal`` says whether no plan has a lower objective (3) (CP-SAT's bound, or the greedy plan at
    0). The same problem gives the same plan, unless the wall-clock limit ends the search before the
    deterministic one (see _DETERMINISTIC_SHARE) or ``num_workers`` > 1.
    """
    start = time.perf_counter()
    # CP-SAT does not refuse a negative or NaN time limit up front: it answers MODEL_INVALID,
    # which would read as "no assignment found in time".
    if not time_limit_s > 0:
        raise PlanInputError("time_limit_s", f"expected a positive number of seconds, got {time_limit_s!r}")
    deadline = start + float(time_limit_s)
    greedy = _greedy(problem)
    start_source = "greedy"  # where the plan CP-SAT starts from came from
    if greedy is None:
        # A valid greedy plan proves the problem feasible; only without one is the capacity check worth its time.
        diag = diagnose_capacity(problem)
        if diag is not None:
            return PlanResult("ip", {}, None, False, False, "infeasible", time.perf_counter() - start, diag)

    def fallback(reason: str, bound: int = 0) -> PlanResult:
        """The greedy plan when CP-SAT has none at least as good; 'unknown' without one. 0 always bounds (3)."""
        if greedy is not None:
            log.debug("ip: returning the %s plan (%s)", start_source, reason)
            optimal = objective_value(problem, greedy) <= bound
            return _finish(problem, "ip", greedy, start, optimal=optimal, status="optimal" if optimal else "feasible",
                           best_bound=bound, source=start_source)
        msg = (
            f"no feasible assignment found within the {time_limit_s:g}s time limit ({reason}); "
            "the problem may still be feasible: raise the time limit."
        )
        return PlanResult("ip", {}, None, False, False, "unknown", time.perf_counter() - start, msg, bound)

    hosted = _hosted(problem)
    try:
        obj_bound = _check_statable(problem, hosted)
    except PlanInputError as exc:
        if greedy is None:
            raise
        # The greedy plan is checked exactly (fractions), so it stands where the integer program cannot be
        # stated in int64 (co-hosted limits whose least common multiple overflows): the even split that the
        # control plane used instead puts GPUs over their limits.
        log.warning("ip: %s; returning the greedy plan", exc)
        return fallback(f"the integer program cannot be stated: {exc}")
    if greedy is not None and plan_key(problem, greedy) == (0, _min_pairs(problem)):
        # Nothing can beat it on either term: every GPU serves one model, each model on as few GPUs as it can.
        return fallback("optimal by construction")
    # Past this size CP-SAT's presolve alone outlasts the time limit (32k variables: 11 s with 5 s left,
    # most of it in steps that do not check the limit), so it is not started at all. Judged on the limit
    # given, not the time left: the same problem and limit must take the same path on every run.
    num_vars = sum(len(m.gpus) for m in problem.models if m.robots)
    if num_vars > _MAX_IP_VARS_PER_S * time_limit_s:
        return fallback(f"an integer program of {num_vars} (model, GPU) pairs is too large for the time limit")
    # CP-SAT's deterministic budget, from the inputs alone (see _cp_sat_parameters).
    work = time_limit_s * _DETERMINISTIC_SHARE
    try:
        ip = _build_ip(problem, hosted, obj_bound, deadline)
    except _OutOfTime:
        return fallback("the time limit passed while building the integer program")
    if greedy is None:
        # The greedy plan gets stuck on tight partial placements. A search for any plan (the constraints
        # without the objective) finds one there in milliseconds, where the full model's search can end
        # the time limit with none, and the control plane then split robots evenly, over the GPUs' limits.
        greedy = _first_plan(problem, ip, deadline, work * _FIRST_PLAN_SHARE, random_seed)
        start_source = "cp-sat"
    if greedy is not None:
        _add_hint(problem, ip, greedy)
    remaining = deadline - time.perf_counter()
    if remaining < _MIN_SOLVE_S:
        return fallback("the time limit passed while building the integer program")

    solver = cp_model.CpSolver()
    _cp_sat_parameters(solver, remaining, work, num_workers, random_seed)
    if num_vars > _SYMMETRY_MAX_VARS:
        # CP-SAT's symmetry detection ignored the time limit on large models (31 s over an 8 s limit at
        # 8192 pairs); the ordering constraints in _build_ip already break the symmetry between GPUs.
        solver.parameters.symmetry_level = 0
    status = solver.solve(ip.mdl)
    name = solver.status_name(status)
    log.debug("CP-SAT %s in %.3fs: %s", name, solver.wall_time, solver.response_stats())

    if status == cp_model.MODEL_INVALID:
        # A formulation the checks above did not foresee; not a time-out, so say what CP-SAT refused.
        raise PlanInputError("models", f"CP-SAT refused the integer program (int64 bounds?): {ip.mdl.validate()}")
    if status == cp_model.INFEASIBLE:
        if greedy is not None:  # a checked plan exists: the formulation is wrong, the plan is not
            log.error("CP-SAT found the integer program infeasible although a valid plan exists; returning that plan")
            return fallback("CP-SAT status INFEASIBLE")
        return PlanResult("ip", {}, None, False, False, "infeasible", time.perf_counter() - start,
                          _fragmentation_message(problem))
    bound = _bound_on_objective(ip, solver.best_objective_bound)
    if status != cp_model.OPTIMAL and solver.deterministic_time < 0.95 * work:
        # The wall clock ended the search before the deterministic budget did, at a point that varies with the
        # machine's load: the same input may give another plan next time. CP-SAT's start-up is wall time its
        # deterministic count leaves out, so short limits (under about 2 s on a busy 2-core machine) hit this.
        log.warning("ip: CP-SAT stopped on the %.2f s wall clock left, having done %.3f of its %.3f deterministic "
                    "budget: this plan may differ between runs of the same input (a longer time limit avoids it)",
                    remaining, solver.deterministic_time, work)
    if status not in (cp_model.OPTIMAL, cp_model.FEASIBLE):
        return fallback(f"CP-SAT status {name}", bound)

    assignment = _read_plan(problem, ip, solver)
    if greedy is not None and plan_key(problem, greedy) < plan_key(problem, assignment):
        return fallback(f"CP-SAT's best plan within the time limit was worse (status {name})", bound)
    optimal = objective_value(problem, assignment) <= bound
    return _finish(problem, "ip", assignment, start, optimal=optimal, status="optimal" if optimal else "feasible",
                   best_bound=bound, source="cp-sat")


def _first_plan(problem: PlanProblem, ip: _IpModel, deadline: float, work: float,
                random_seed: int) -> dict[str, dict[int, int]] | None:
    """Any plan within the limits: CP-SAT on the constraints of ``ip`` without its objective, stopped at the
    first solution, for at most _FIRST_PLAN_SHARE of the time left and ``work`` of deterministic time. None
    when it finds none in that time."""
    remaining = deadline - time.perf_counter()
    if remaining < 2 * _MIN_SOLVE_S:
        return None
    mdl = ip.mdl.clone()  # the same variables, by index, so ip.r reads the solution
    mdl.clear_objective()
    solver = cp_model.CpSolver()
    _cp_sat_parameters(solver, remaining * _FIRST_PLAN_SHARE, work, 1, random_seed)
    solver.parameters.stop_after_first_solution = True
    status = solver.solve(mdl)
    log.debug("CP-SAT first plan: %s in %.3fs", solver.status_name(status), solver.wall_time)
    if status not in (cp_model.OPTIMAL, cp_model.FEASIBLE):
        return None
    return _read_plan(problem, ip, solver)


def _read_plan(problem: PlanProblem, ip: _IpModel, solver: cp_model.CpSolver) -> dict[str, dict[int, int]]:
    """The assignment of CP-SAT's solution to ``ip`` (or to a clone of it: the same variables by index)."""
    plan: dict[str, dict[int, int]] = {m.name: {} for m in problem.models}
    for (i, j), v in ip.r.items():
        plan[problem.models[i].name][j] = int(solver.value(v))
    problems = check_assignment(problem, plan)
    if problems:  # would be a formulation bug; never hand out an overload silently
        raise AssertionError(f"CP-SAT returned an invalid assignment: {problems}")
    return plan


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
