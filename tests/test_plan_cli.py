"""`robion plan` (python -m services.controlplane.planning): output, exit codes, input errors."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from services.controlplane.planning import problem_from_mapping
from services.controlplane.solver import PlanInputError

ROOT = Path(__file__).resolve().parents[1]

PAPER = """\
gpus: 2
models:
  A: {limit: 4, robots: 6, gpus: [0, 1]}   # limit = C_i, robots = N_i, GPUs hosting the model
  B: {limit: 4, robots: 2, gpus: [0, 1]}
"""


def run_plan(tmp_path: Path, text: str, *args: str) -> subprocess.CompletedProcess[str]:
    f = tmp_path / "plan.yaml"
    f.write_text(text)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run(
        [sys.executable, "-m", "services.controlplane.planning", str(f), *args],
        capture_output=True, text=True, cwd=ROOT, env=env, timeout=60,
    )


def test_paper_example_json(tmp_path: Path) -> None:
    out = run_plan(tmp_path, PAPER, "--json")
    assert out.returncode == 0, out.stderr
    data = json.loads(out.stdout)
    assert set(data) == {"assignment", "objective", "feasible"}
    assert data["objective"] == 4 and data["feasible"] is True
    per_gpu = [{m: row[g] for m, row in data["assignment"].items() if g in row} for g in ("0", "1")]
    assert sorted(per_gpu, key=len) == [{"A": 4}, {"A": 2, "B": 2}]


def test_paper_example_table(tmp_path: Path) -> None:
    out = run_plan(tmp_path, PAPER)
    assert out.returncode == 0, out.stderr
    assert "GPU0" in out.stdout and "GPU1" in out.stdout
    assert out.stdout.count("100%") == 2
    assert "objective: 4" in out.stdout and "proven optimal" in out.stdout


def test_headroom_flag_and_cluster_config_default(tmp_path: Path) -> None:
    out = run_plan(tmp_path, PAPER, "--headroom", "0.75", "--json")
    assert out.returncode == 1  # limits of 3 hold 6 of the 8 robots
    assert json.loads(out.stdout) == {"assignment": {}, "objective": None, "feasible": False}
    assert "short by" in out.stderr
    assert run_plan(tmp_path, PAPER, "--headroom", "0").returncode == 2
    cluster = """\
models:
  - {name: A, arch: toy, robots: 6, limit: 8}
  - {name: B, arch: toy, robots: 2, limit: 8}
executors:
  - {name: ex0, models: [A, B]}
  - {name: ex1, models: [A, B]}
control: {headroom: 0.5}
"""
    table = run_plan(tmp_path, cluster)
    assert table.returncode == 0, table.stderr
    rows = {line.split()[0]: line.split()[1] for line in table.stdout.splitlines() if line[:1] in "AB"}
    assert rows == {"A": "4", "B": "4"}  # floor(8 x 0.5): the paper example again
    assert "100%" in table.stdout
    assert run_plan(tmp_path, cluster, "--headroom", "0.25").returncode == 1  # the flag wins


def test_a_cluster_config_whose_headroom_no_plan_keeps_is_planned_to_the_full_limits(tmp_path: Path) -> None:
    """The control plane plans to the full limits where no plan keeps control.headroom; `robion plan` said
    "infeasible" (exit 1) for the same config. An explicit --headroom still asks for that headroom alone."""
    cluster = """\
models:
  - {name: A, arch: toy, robots: 6, limit: 4}
  - {name: B, arch: toy, robots: 2, limit: 4}
executors:
  - {name: ex0, models: [A]}
  - {name: ex1, models: [A, B]}
control: {headroom: 0.5}
"""
    out = run_plan(tmp_path, cluster, "--json")
    assert out.returncode == 0, out.stderr
    assert "planning to the full robot limits" in out.stderr
    assert json.loads(out.stdout) == {"assignment": {"A": {"0": 4, "1": 2}, "B": {"1": 2}}, "objective": 4,
                                      "feasible": True}
    assert run_plan(tmp_path, cluster, "--headroom", "0.5").returncode == 1


def test_strategies_json(tmp_path: Path) -> None:
    smg = run_plan(tmp_path, PAPER, "--strategy", "smg", "--json")
    assert smg.returncode == 1  # GPU 0 serves 6 robots against a limit of 4
    assert json.loads(smg.stdout) == {"assignment": {"A": {"0": 6}, "B": {"1": 2}}, "objective": 0, "feasible": False}
    eps = run_plan(tmp_path, PAPER, "--strategy", "eps", "--json")
    assert eps.returncode == 0
    assert json.loads(eps.stdout) == {
        "assignment": {"A": {"0": 3, "1": 3}, "B": {"0": 1, "1": 1}}, "objective": 6, "feasible": True,
    }


def test_infeasible_exit_1_with_explanation(tmp_path: Path) -> None:
    out = run_plan(tmp_path, "gpus: 2\nmodels:\n  A: {limit: 4, robots: 9}\n  B: {limit: 4, robots: 2}\n")
    assert out.returncode == 1
    assert "Traceback" not in out.stderr
    assert "A, B" in out.stderr and "GPUs 0, 1" in out.stderr and "Add at least 1 GPU" in out.stderr


@pytest.mark.parametrize(
    "text, message",
    [
        ("gpus: 2\nmodels:\n  A: {limit: 0, robots: 6}\n", "models.A.limit: expected a positive integer"),
        ("gpus: 2\nmodels:\n  A: {limit: 4, robots: 6, gpus: [0, 2]}\n", "models.A.gpus[1]: expected a GPU index in 0..1"),
        ("gpus: 2\nmodels:\n  A: {limit: 4, robots: 1, gpus: []}\n", "models.A.gpus: model has 1 robots but no GPU hosts it"),
        ("gpus: [\n", "not valid YAML"),
    ],
)
def test_bad_file_exit_2(tmp_path: Path, text: str, message: str) -> None:
    out = run_plan(tmp_path, text)
    assert out.returncode == 2
    assert message in out.stderr
    assert "Traceback" not in out.stderr


def test_missing_file_exit_2(tmp_path: Path) -> None:
    out = subprocess.run(
        [sys.executable, "-m", "services.controlplane.planning", str(tmp_path / "nope.yaml")],
        capture_output=True, text=True, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=60,
    )
    assert out.returncode == 2 and "cannot read file" in out.stderr and "Traceback" not in out.stderr


@pytest.mark.parametrize(
    "data, path",
    [
        ([1, 2], ""),
        ({"models": {}}, "gpus"),
        ({"gpus": 2}, "models"),
        ({"gpus": 2, "models": [1]}, "models"),
        ({"gpus": 2, "models": {}, "extra": 1}, "extra"),
        ({"gpus": True, "models": {}}, "gpus"),
        ({"gpus": 2, "models": {"A": 3}}, "models.A"),
        ({"gpus": 2, "models": {"A": {"robots": 1}}}, "models.A.limit"),
        ({"gpus": 2, "models": {"A": {"limit": 2}}}, "models.A.robots"),
        ({"gpus": 2, "models": {"A": {"limit": 2.5, "robots": 1}}}, "models.A.limit"),
        ({"gpus": 2, "models": {"A": {"limit": 2, "robots": -1}}}, "models.A.robots"),
        ({"gpus": 2, "models": {"A": {"limit": 2, "robots": 1, "gpus": 0}}}, "models.A.gpus"),
        ({"gpus": 2, "models": {"A": {"limit": 2, "robots": 1, "gpus": ["x"]}}}, "models.A.gpus[0]"),
        ({"gpus": 2, "models": {"A": {"limit": 2, "robots": 1, "gpus": [1, 1]}}}, "models.A.gpus"),
        ({"gpus": 2, "models": {"A": {"limit": 2, "robots": 1, "lmit": 3}}}, "models.A.lmit"),
    ],
)
def test_problem_from_mapping_errors(data: object, path: str) -> None:
    with pytest.raises(PlanInputError) as e:
        problem_from_mapping(data)
    assert e.value.path == path


def test_problem_from_mapping_defaults_to_all_gpus() -> None:
    p = problem_from_mapping({"gpus": 3, "models": {"A": {"limit": 4, "robots": 6}, "B": {"limit": 2, "robots": 0, "gpus": [1]}}})
    assert p.num_gpus == 3
    assert [(m.name, m.limit, m.robots, m.gpus) for m in p.models] == [("A", 4, 6, (0, 1, 2)), ("B", 2, 0, (1,))]


def test_cluster_config_with_placement_shorthand(tmp_path: Path) -> None:
    """A cluster config written with `gpus: N` + `placement:` (docs/operations.md) has no `executors`
    key until it is expanded; it was read as a planning file and refused (`placement: unknown key`)."""
    cluster = """\
models:
  - {name: A, arch: toy, robots: 6, limit: 4}
  - {name: B, arch: toy, robots: 2, limit: 4}
gpus: 2
placement: mix
"""
    out = run_plan(tmp_path, cluster, "--json")
    assert out.returncode == 0, out.stderr
    data = json.loads(out.stdout)
    assert data["objective"] == 4 and data["feasible"] is True  # the paper example on gpu0, gpu1
    assert {m: sum(row.values()) for m, row in data["assignment"].items()} == {"A": 6, "B": 2}


@pytest.mark.parametrize("value", ["-1", "0", "nan", "inf", "3601"])
def test_time_limit_that_is_not_positive_exit_2(tmp_path: Path, value: str) -> None:
    """A negative or NaN limit made CP-SAT refuse its own parameters (MODEL_INVALID); that was reported as
    'no feasible assignment ... raise the time limit', exit 1, as if the planning file were the problem.
    `inf` never ended; the bound is the config's for control.solve_time_limit_s."""
    out = run_plan(tmp_path, PAPER, "--time-limit", value)
    assert out.returncode == 2, (out.returncode, out.stdout, out.stderr)
    assert "--time-limit" in out.stderr and "positive" in out.stderr, out.stderr
    assert "Traceback" not in out.stderr


# --------------------------------------------------------------------------- the control section, repeated keys, the GPU cap

CLUSTER_SMG = """\
models:
  - {name: A, arch: toy, robots: 6, limit: 4}
  - {name: B, arch: toy, robots: 2, limit: 4}
executors:
  - {name: ex0, models: [A, B]}
  - {name: ex1, models: [A, B]}
control: {strategy: smg, solve_time_limit_s: 0.5}
"""


def test_cluster_config_plans_with_its_control_strategy(tmp_path: Path) -> None:
    """docs/planning.md: `robion plan` runs the control plane's traffic controller; on a cluster config it
    ignored control.strategy and solved the integer program."""
    out = run_plan(tmp_path, CLUSTER_SMG)
    assert "strategy: smg" in out.stdout, out.stdout
    assert out.returncode == 1 and "smg assignment exceeds GPU limits" in out.stderr  # what the plane would do


def test_cluster_config_defaults_and_flags(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    """control.solve_time_limit_s was ignored too (the CLI's 8 s default was used). Flags still win, and a
    planning file keeps the CLI defaults."""
    import services.controlplane.planning as planning

    calls: list[tuple[str, float]] = []
    real_solve = planning.solve

    def spy(problem, strategy="ip", time_limit_s=8.0, **kwargs):
        calls.append((strategy, time_limit_s))
        return real_solve(problem, strategy, time_limit_s=time_limit_s, **kwargs)

    monkeypatch.setattr(planning, "solve", spy)
    f = tmp_path / "cluster.yaml"
    f.write_text(CLUSTER_SMG)
    assert planning.main([str(f), "--json"]) == 1  # smg overloads GPU 0
    assert planning.main([str(f), "--json", "--strategy", "ip", "--time-limit", "3"]) == 0
    f.write_text(CLUSTER_SMG.replace("strategy: smg", "strategy: none"))
    capsys.readouterr()
    assert planning.main([str(f), "--json"]) == 0
    assert "control.strategy is 'none'" in capsys.readouterr().err
    p = tmp_path / "plan.yaml"
    p.write_text(PAPER)
    assert planning.main([str(p), "--json"]) == 0
    assert calls == [("smg", 0.5), ("ip", 3.0), ("ip", 0.5), ("ip", 8.0)]


@pytest.mark.parametrize("text, message", [
    ("gpus: 2\nmodels:\n  A: {limit: 4, robots: 6, gpus: [0, 1]}\n  B: {limit: 4, robots: 2, gpus: [0, 1]}\n"
     "  A: {limit: 4, robots: 1, gpus: [0]}\n", "duplicate key 'A' at line 5, column 3 (first given at line 3, column 3)"),
    ("gpus: 2\ngpus: 1\nmodels:\n  A: {limit: 4, robots: 6}\n", "duplicate key 'gpus' at line 2"),
    ("gpus: 2\nmodels:\n  A: {limit: 4, robots: 2, robots: 9}\n", "duplicate key 'robots' at line 3"),
    ("models:\n  - {name: A, arch: toy, robots: 2, limit: 4}\nexecutors:\n  - {name: ex0, models: [A]}\n"
     "control: {headroom: 0.5}\ncontrol: {strategy: smg}\n", "duplicate key 'control' at line 6"),
])
def test_duplicate_keys_are_refused(tmp_path: Path, text: str, message: str) -> None:
    """yaml.safe_load keeps the last of two equal keys: a model named twice was planned once, with the
    second entry's numbers, and nothing was said."""
    out = run_plan(tmp_path, text)
    assert out.returncode == 2, (out.stdout, out.stderr)
    assert message in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_too_many_gpus_exit_2(tmp_path: Path) -> None:
    """`gpus: 100000000` ended in a MemoryError traceback (a host list per model); 4096 is the documented cap."""
    out = run_plan(tmp_path, "gpus: 1000000000000\nmodels:\n  A: {limit: 4, robots: 6}\n")
    assert out.returncode == 2, out.stderr[-500:]
    assert "gpus: at most 4096 GPUs can be planned, got 1000000000000" in out.stderr
    assert "Traceback" not in out.stderr


def test_summary_lower_bound_is_never_negative(tmp_path: Path) -> None:
    """Cut off early the summary printed CP-SAT's bound on twice the objective, halved: 'lower bound -2878.5'."""
    import re

    import yaml
    from tests.test_solver import bench_instance

    p = bench_instance(32, 16, "full", 32163)
    text = yaml.safe_dump({"gpus": p.num_gpus, "models": {m.name: {"limit": m.limit, "robots": m.robots,
                                                                    "gpus": list(m.gpus)} for m in p.models}})
    out = run_plan(tmp_path, text, "--time-limit", "0.5")
    assert out.returncode == 0, out.stderr
    summary = out.stdout.strip().splitlines()[-1]
    objective = int(re.search(r"objective: (\d+)", summary).group(1))
    bound = re.search(r"lower bound (\S+)\)", summary)
    assert bound or "proven optimal" in summary, summary
    if bound:
        assert bound.group(1).isdigit() and int(bound.group(1)) <= objective, summary


def test_a_cluster_model_without_a_limit_is_left_out_as_the_control_plane_does(tmp_path):
    # The control plane plans the models it has limits for and spreads the others round-robin per request
    # (traffic.assign); robion plan refused the whole file, and listed limitless models with "limit 1".
    cluster = """\
models:
  - {name: A, arch: toy, robots: 6, limit: 4}
  - {name: B, arch: toy, robots: 3}
  - {name: C, arch: toy}
executors:
  - {name: ex0, models: [A, B, C]}
  - {name: ex1, models: [A, B]}
"""
    out = run_plan(tmp_path, cluster, "--json")
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["assignment"] == {"A": {"0": 4, "1": 2}}
    assert "no robot limit for B: left out of the plan" in out.stderr
    table = run_plan(tmp_path, cluster)
    assert table.returncode == 0 and "B " not in table.stdout and "C " not in table.stdout
    nothing = run_plan(tmp_path, cluster.replace("robots: 6, limit: 4", "robots: 0"))
    assert nothing.returncode == 0 and "nothing to assign" in nothing.stdout


def test_a_cluster_config_with_imports_beside_it_is_planned(tmp_path: Path) -> None:
    """Every service imports a config's `imports` from the config's folder; `robion plan` looked for them only on
    its own path, so planning a cluster that serves a user's architecture failed with a config error."""
    import yaml

    from tests.test_user_model import docs_example

    (tmp_path / "my_vla_plan.py").write_text(docs_example())
    text = yaml.safe_dump({"imports": ["my_vla_plan"],
                           "models": [{"name": "mine", "arch": "my_vla", "size": "tiny", "robots": 3, "limit": 4}],
                           "executors": [{"name": "ex0", "models": ["mine"]}, {"name": "ex1", "models": ["mine"]}]})
    out = run_plan(tmp_path, text, "--json")
    assert out.returncode == 0, out.stderr
    assert sum(json.loads(out.stdout)["assignment"]["mine"].values()) == 3
