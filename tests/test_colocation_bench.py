"""The co-location (E4) and queue-policy (E5) driver on the CPU with tiny models."""

import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "bench"))

from colocation import split, summary  # noqa: E402


def test_split_keeps_totals_and_proportions():
    assert split(10, [3, 1]) == [8, 2]
    assert split(7, [1, 1, 1, 1]) == [2, 2, 2, 1]
    assert sum(split(13, [2, 1, 1])) == 13


def test_summary_ratios_are_null_where_undefined():
    rows = [{"engine": "robion", "miss_ratio": 0.0}, {"engine": "monolithic", "miss_ratio": 0.25}]
    assert summary(rows, "e4") == {"mean_miss_ratio": {"robion": 0.0, "monolithic": 0.25},
                                   "monolithic_over_robion": None}  # Robion missed nothing: no finite ratio
    rows = [{"engine": "esf", "slo_attainment": 0.9}, {"engine": "rr", "slo_attainment": 0.6}]
    assert summary(rows, "e5")["esf_over_rr"] == 1.5 and summary(rows, "e5")["esf_over_lqf"] is None


def run(tmp_path, *args):
    out = tmp_path / "r.json"
    res = subprocess.run([sys.executable, "bench/colocation.py", *args, "--size", "tiny", "--device", "cpu",
                          "--epochs", "1", "--duration", "1", "--out", str(out)], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    return json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"{c} is not JSON"))


def test_e4_runs_both_engines_on_the_same_workload(tmp_path):
    r = run(tmp_path, "e4", "--scenarios", "skewed-2", "--robots", "4")
    assert sorted(row["engine"] for row in r["rows"]) == ["monolithic", "robion"]
    assert all(row["counts"] == [3, 1] for row in r["rows"])
    assert set(r["summary"]["mean_miss_ratio"]) == {"robion", "monolithic"}


def test_the_engines_take_turns_running_first_from_one_robot_count_to_the_next(tmp_path):
    """Who ran first went by the count's parity, so every documented sweep (all even counts) ran Robion first."""
    r = run(tmp_path, "e4", "--scenarios", "same-2", "--robots", "2,4")
    assert [(row["robots"], row["engine"]) for row in r["rows"]] == [(2, "robion"), (2, "monolithic"),
                                                                      (4, "monolithic"), (4, "robion")]


def test_e5_policies_and_deadlines(tmp_path):
    r = run(tmp_path, "e5", "--scenarios", "equal-deadlines", "--robots", "2")
    assert sorted(row["engine"] for row in r["rows"]) == ["esf", "lqf", "rr"]
    assert r["rows"][0]["deadlines_ms"] == {"pi0": 117.0, "xr0": 117.0}
    assert {"esf_over_rr", "esf_over_lqf"} <= set(r["summary"])


def test_e5_with_shed_late_adds_that_engine(tmp_path):
    r = run(tmp_path, "e5", "--scenarios", "equal-deadlines", "--robots", "2", "--shed-late")
    assert sorted(row["engine"] for row in r["rows"]) == ["esf", "esf-shed", "lqf", "rr"]
    assert "esf-shed" in r["summary"]["mean_slo_attainment"]


def test_e4_with_shed_late_adds_that_engine(tmp_path):
    r = run(tmp_path, "e4", "--scenarios", "skewed-2", "--robots", "4", "--shed-late")
    assert sorted(row["engine"] for row in r["rows"]) == ["monolithic", "robion", "robion-shed"]
    assert "robion-shed" in r["summary"]["mean_miss_ratio"]
