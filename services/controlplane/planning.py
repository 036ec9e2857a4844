"""`robion plan`: robot-to-GPU assignment from populations, limits and placement.

Reads a minimal planning file (see docs/planning.md), solves it with the traffic
controller and prints the assignment without starting anything:

    python -m services.controlplane.planning FILE.yaml [--strategy ip|smg|eps] [--headroom H] [--json]

For a cluster config the strategy, time limit and headroom default to its ``control``
section, so the plan is the one the control plane would make; explicit flags win.

Exit codes: 0 assignment within the GPU limits, 1 infeasible (or, for smg/eps, an
assignment that overloads a GPU; for ip also a time-out without any assignment),
2 unreadable or invalid input.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence


from shared.config import (MAX_SOLVE_TIME_LIMIT_S, ClusterConfig, ConfigError, ControlConfig, config_from_dict, parse_yaml,
                           solve_time_limit)

from services.controlplane.solver import (
    DEFAULT_TIME_LIMIT_S,
    STRATEGIES,
    ModelDemand,
    PlanInputError,
    PlanProblem,
    PlanResult,
    check_num_gpus,
    solve,
    with_headroom,
)

_MODEL_KEYS = ("limit", "robots", "gpus")
_TOP_KEYS = ("gpus", "models")


def _int(value: Any, path: str, *, minimum: int, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise PlanInputError(path, f"expected a {what}, got {value!r}")
    return value


def problem_from_mapping(data: Any) -> PlanProblem:
    """Build a PlanProblem from the parsed planning mapping, naming the bad field on error.

    Shape: ``{"gpus": int >= 1, "models": {name: {"limit": int >= 1, "robots": int >= 0,
    "gpus": [int, ...] (optional; omitted = every GPU)}}}``. Model order is kept.
    """
    if not isinstance(data, Mapping):
        raise PlanInputError("", f"expected a mapping with keys {', '.join(_TOP_KEYS)}, got {type(data).__name__}")
    for key in data:
        if key not in _TOP_KEYS:
            raise PlanInputError(str(key), f"unknown key (expected {', '.join(_TOP_KEYS)})")
    if "gpus" not in data:
        raise PlanInputError("gpus", "missing (number of GPUs)")
    # Checked against MAX_GPUS before anything is sized by it (every model without `gpus` gets a list of them).
    num_gpus = check_num_gpus(data["gpus"])
    models_raw = data.get("models")
    if models_raw is None:
        raise PlanInputError("models", "missing (mapping of model name to limit/robots/gpus)")
    if not isinstance(models_raw, Mapping):
        raise PlanInputError("models", f"expected a mapping of model name to settings, got {type(models_raw).__name__}")

    models: list[ModelDemand] = []
    for raw_name, spec in models_raw.items():
        name = str(raw_name)
        base = f"models.{name}"
        if not isinstance(spec, Mapping):
            raise PlanInputError(base, f"expected a mapping with {', '.join(_MODEL_KEYS)}, got {type(spec).__name__}")
        for key in spec:
            if key not in _MODEL_KEYS:
                raise PlanInputError(f"{base}.{key}", f"unknown key (expected {', '.join(_MODEL_KEYS)})")
        for key in ("limit", "robots"):
            if key not in spec:
                raise PlanInputError(f"{base}.{key}", "missing")
        limit = _int(spec["limit"], f"{base}.limit", minimum=1, what="positive integer")
        robots = _int(spec["robots"], f"{base}.robots", minimum=0, what="non-negative integer")
        gpus_raw = spec.get("gpus")
        if gpus_raw is None:
            gpus = tuple(range(num_gpus))
        else:
            if not isinstance(gpus_raw, (list, tuple)):
                raise PlanInputError(f"{base}.gpus", f"expected a list of GPU indices, got {gpus_raw!r}")
            gpus = tuple(gpus_raw)
        models.append(ModelDemand(name, limit, robots, gpus))
    # PlanProblem validates the rest (GPU range, duplicates, robots without a host).
    return PlanProblem(num_gpus, tuple(models))


def problem_from_cluster(cfg: ClusterConfig, executors: Sequence[str] | None = None) -> PlanProblem:
    """The assignment problem of a cluster config: GPU j is the j-th executor (of ``executors``, default all)."""
    names = list(executors) if executors is not None else [e.name for e in cfg.executors]
    hosts: dict[str, list[int]] = {}
    for j, name in enumerate(names):
        try:
            placed = cfg.executor(name).models
        except KeyError:
            continue
        for model in placed:
            hosts.setdefault(model, []).append(j)
    # A model without a limit is left out, as the control plane leaves it out until one is measured
    # (traffic.assign): its robots go round-robin per request meanwhile. unplanned() names them.
    models = [ModelDemand(m.name, m.limit, m.robots, tuple(hosts.get(m.name, ()))) for m in cfg.models
              if m.limit is not None]
    return PlanProblem(len(names), tuple(models))


def unplanned(cfg: ClusterConfig) -> list[str]:
    """Models of a cluster config with robots but no configured limit: problem_from_cluster leaves them out."""
    return [m.name for m in cfg.models if m.robots and m.limit is None]


@dataclass(frozen=True)
class PlanningInput:
    """A parsed planning file: the problem, and the ``control`` section when it is a cluster config."""

    problem: PlanProblem
    control: ControlConfig | None = None
    unplanned: tuple[str, ...] = ()  # a cluster config's models with robots but no limit (left out of problem)
    full: PlanProblem | None = None  # the problem at the full limits, where headroom cut them (problem != full)


def load_planning_input(path: str | Path, headroom: float | None = None) -> PlanningInput:
    """Parse a YAML planning file or a full cluster config; PlanInputError carries a readable reason.

    Limits are cut to ``headroom`` of C_i (``with_headroom``): the given share, else a cluster
    config's ``control.headroom`` (what the control plane would plan with), else none."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as e:
        raise PlanInputError("", f"cannot read file: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise PlanInputError("", f"not a UTF-8 text file (byte {e.start})") from None
    try:
        data = parse_yaml(text)
    except ConfigError as e:
        raise PlanInputError("", str(e)) from None
    # A cluster config written with the placement shorthand (`gpus: N` + `placement:`) has no
    # `executors` key until it is expanded; a planning file never has `placement`.
    if isinstance(data, dict) and ("executors" in data or "placement" in data):
        try:
            # `imports` name modules beside the config file, as for every service reading it (load_config).
            cfg = config_from_dict(data, Path(path).resolve().parent)
            full = problem_from_cluster(cfg)
            problem = with_headroom(full, cfg.control.headroom if headroom is None else headroom)
        except ConfigError as e:
            raise PlanInputError("", str(e)) from None
        return PlanningInput(problem, cfg.control, tuple(unplanned(cfg)), full)
    full = problem_from_mapping(data)
    return PlanningInput(with_headroom(full, 1.0 if headroom is None else headroom), full=full)


def load_planning_file(path: str | Path, headroom: float | None = None) -> PlanProblem:
    """The problem of a planning file or cluster config (``load_planning_input`` without the control section)."""
    return load_planning_input(path, headroom).problem


def format_table(problem: PlanProblem, result: PlanResult) -> str:
    """Models x GPUs robot counts, then each GPU's load as a share of its capacity."""
    G = problem.num_gpus
    name_w = max([len("model"), len("load")] + [len(m.name) for m in problem.models])
    col_w = max(6, len(str(G - 1)) + 4)
    header = f"{'model':<{name_w}}  {'limit':>5}  {'robots':>6}  " + "".join(f"{'GPU' + str(j):>{col_w}}" for j in range(G))
    lines = [header, "-" * len(header)]
    for m in problem.models:
        row = result.assignment.get(m.name, {})
        cells = "".join(
            f"{(str(row.get(j, 0)) if j in m.gpus else '.'):>{col_w}}" for j in range(G)
        )
        lines.append(f"{m.name:<{name_w}}  {m.limit:>5}  {m.robots:>6}  {cells}")
    lines.append("-" * len(header))
    loads = "".join(f"{f'{100 * float(x):.0f}%':>{col_w}}" for x in result.gpu_load)
    lines.append(f"{'load':<{name_w}}  {'':>5}  {'':>6}  {loads}")
    return "\n".join(lines)


def _summary(result: PlanResult) -> str:
    parts = [f"strategy: {result.strategy}", f"objective: {result.objective}"]
    if result.strategy == "ip":
        if result.source == "greedy":
            # Returned because CP-SAT had nothing at least as good within the time limit, was not run (an
            # integer program too large for the time left, or not statable in int64), or, when proven
            # optimal, because nothing can beat it; worth saying either way.
            parts.append("greedy plan" if result.optimal else "greedy plan (none better from CP-SAT)")
        if result.optimal:
            parts.append("proven optimal")
        else:
            # best_bound is max(0, ceil(CP-SAT's bound)) on the objective itself: never negative.
            parts.append(f"not proven optimal (lower bound {result.best_bound})")
    parts.append("within GPU limits" if result.feasible else "EXCEEDS GPU limits")
    parts.append(f"solved in {result.solve_time_s:.3f}s")
    return ", ".join(parts)


def _time_limit(text: str) -> float:
    """--time-limit: seconds, positive (CP-SAT answers MODEL_INVALID to a negative or NaN limit) and at most
    what the config allows control.solve_time_limit_s (`inf` never ended)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not solve_time_limit(value):
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, at most {MAX_SOLVE_TIME_LIMIT_S}, "
                                         f"got {text!r}")
    return value


def _defaults(args: argparse.Namespace, control: ControlConfig | None) -> tuple[str, float]:
    """Strategy and time limit: the flags, else a cluster config's control section (what the control
    plane solves with), else ip and DEFAULT_TIME_LIMIT_S."""
    strategy, time_limit = args.strategy, args.time_limit
    if control is not None:
        if strategy is None:
            if control.strategy in STRATEGIES:
                strategy = control.strategy
            else:  # "none": the control plane pins no robots; there is nothing of its own to show
                print(f"robion plan: {args.file}: control.strategy is {control.strategy!r} (the control plane assigns "
                      "no robots to GPUs; requests go round-robin); showing the ip plan", file=sys.stderr)
        if time_limit is None:
            time_limit = control.solve_time_limit_s
    return strategy or "ip", DEFAULT_TIME_LIMIT_S if time_limit is None else time_limit


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="robion plan",
        description="Assign robots to GPUs from populations, robot limits and model placement.",
    )
    ap.add_argument("file", help="planning file (YAML: gpus, models: {name: {limit, robots, gpus}}) or a cluster config "
                                 "(executors are the GPUs; models without a limit are left out, as the control plane leaves them "
                                 "out until one is measured)")
    ap.add_argument("--strategy", choices=STRATEGIES, help="ip (integer program), smg, eps "
                                                           "(default: a cluster config's control.strategy, else ip)")
    ap.add_argument("--json", action="store_true", help='print {"assignment", "objective", "feasible"} as JSON')
    ap.add_argument("--time-limit", type=_time_limit, help="time limit in seconds for ip (default: a cluster config's "
                                                           f"control.solve_time_limit_s, else {DEFAULT_TIME_LIMIT_S:g})")
    ap.add_argument("--headroom", type=float, help="plan with floor(limit x H) robots per GPU, 0 < H <= 1 "
                                                   "(default: a cluster config's control.headroom, else 1; where no plan keeps "
                                                   "the config's headroom, the full limits, as the control plane does)")
    args = ap.parse_args(argv)

    try:
        planning = load_planning_input(args.file, args.headroom)
        problem = planning.problem
        strategy, time_limit = _defaults(args, planning.control)
        result = solve(problem, strategy, time_limit_s=time_limit)
        if not result.assignment and args.headroom is None and planning.full is not None and planning.full != problem:
            # A cluster config's own headroom is planned as the control plane plans it (traffic.assign): a plan
            # within the full limits beats none. An explicit --headroom asks whether one within it exists.
            print(f"robion plan: {args.file}: no plan keeps the headroom ({result.diagnosis}); planning to the full "
                  "robot limits, as the control plane does", file=sys.stderr)
            problem = planning.full
            result = solve(problem, strategy, time_limit_s=time_limit)
    except PlanInputError as e:
        print(f"robion plan: {args.file}: {e}", file=sys.stderr)
        return 2
    if planning.unplanned:
        print(f"robion plan: {args.file}: no robot limit for {', '.join(planning.unplanned)}: left out of the plan; "
              "the control plane spreads their robots round-robin per request until a limit is measured "
              "(control.limits.auto) or configured", file=sys.stderr)

    if args.json:
        print(json.dumps(result.to_json_dict()))
    elif not any(m.robots for m in problem.models):
        print("nothing to assign: no model has both robots and a robot limit")
    elif result.assignment:
        print(format_table(problem, result))
        print(_summary(result))
    if not result.feasible:
        print(result.diagnosis or "infeasible", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
