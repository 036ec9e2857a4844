"""The benchmarks refuse bad arguments before they build a model: exit 2 with the option named. Before, some ran on
to a wrong result with exit 0 (a max_batch of 0 measured as a capacity of 0 in every row, variants left without
robots), some failed with a traceback after the run, and engine_gap.py then hung on its engine's thread."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

CASES = {
    "engine_gap seconds": (["engine_gap.py", "--models", "heavytoy:small", "--seconds", "0"], "--seconds"),
    "engine_gap rate": (["engine_gap.py", "--models", "heavytoy:small", "--rate", "-5"], "--rate"),
    "engine_gap max batch": (["engine_gap.py", "--models", "heavytoy:small", "--max-batch", "3"], "--max-batch"),
    "engine_gap ahead": (["engine_gap.py", "--models", "heavytoy:small", "--ahead", "of"], "--ahead"),
    "colocation max batch": (["colocation.py", "e4", "--size", "tiny", "--device", "cpu", "--max-batch", "0"],
                             "--max-batch"),
    "colocation epochs": (["colocation.py", "e4", "--size", "tiny", "--device", "cpu", "--epochs", "0"], "--epochs"),
    # Under one period (1 / 2 Hz): a model of few robots sent nothing in some epochs, and its row averaged the others.
    "colocation duration": (["colocation.py", "e4", "--size", "tiny", "--device", "cpu", "--duration", "0.3"],
                            "--duration"),
    "colocation out": (["colocation.py", "e4", "--size", "tiny", "--device", "cpu", "--out", "/nonexistent/r.json"],
                       "--out"),
    "interdisagg target": (["interdisagg.py", "--devices", "cpu,cpu", "--size", "tiny", "--target", "1.5"],
                           "--target"),
    "interdisagg sweep": (["interdisagg.py", "--devices", "cpu,cpu", "--size", "tiny", "--sweep", "0,1"], "--sweep"),
    "interdisagg size": (["interdisagg.py", "--devices", "cpu,cpu", "--size", "bogus"], "--size"),
    "interdisagg max batch": (["interdisagg.py", "--devices", "cpu,cpu", "--size", "tiny", "--max-batch", "0"],
                              "--max-batch"),
    "interdisagg one device": (["interdisagg.py", "--devices", "cpu", "--size", "tiny"], "--devices"),
    "interdisagg splits": (["interdisagg.py", "--devices", "cpu,cpu", "--size", "tiny", "--splits", "1:2"],
                           "--splits"),
    "interdisagg deadline": (["interdisagg.py", "--devices", "cpu,cpu", "--size", "tiny", "--arch", "toy"],
                             "--deadline"),
    "traffic shares": (["traffic.py", "strategies", "--devices", "cpu", "--rates", "1,2,2,4", "--shares", "1,1"],
                       "--shares"),
    "traffic arch2": (["traffic.py", "placements", "--devices", "cpu", "--arch2", "toy"], "--arch2"),
    "traffic max batch": (["traffic.py", "strategies", "--devices", "cpu", "--max-batch", "0"], "--max-batch"),
    "router_hop iters": (["router_hop.py", "--iters", "0"], "--iters"),
    "router_hop out": (["router_hop.py", "--iters", "5", "--out", "/nonexistent/r.json"], "--out"),
    "router_flood requests": (["router_flood.py", "--requests", "0"], "--requests"),
    "router_flood rounds": (["router_flood.py", "--rounds", "0"], "--rounds"),
    "router_flood hz": (["router_flood.py", "--hz", "nan"], "--hz"),
    "router_flood out": (["router_flood.py", "--out", "/nonexistent/r.json"], "--out"),
    "solver_speed instances": (["solver_speed.py", "--instances", "0"], "--instances"),
    "solver_speed time limit": (["solver_speed.py", "--time-limit", "0"], "--time-limit"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_bad_argument_is_refused_with_exit_2_naming_it(case, tmp_path):
    argv, option = CASES[case]
    res = subprocess.run([sys.executable, f"bench/{argv[0]}", *argv[1:]], cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 2, (res.returncode, res.stderr[-1500:])
    assert "error: " + option in res.stderr, res.stderr[-1500:]
    assert "Traceback" not in res.stderr
    assert not Path("/nonexistent").exists()  # refused before anything was written


def test_traffic_placements_use_the_deadline_given_for_arch():
    """--deadline is --arch's; placements kept the paper's 156 ms for pi0 whatever it said."""
    import argparse

    sys.path.insert(0, str(ROOT / "bench"))
    import traffic

    args = argparse.Namespace(arch="pi0", arch2="xr0", hz=2.0, deadline=100.0)
    deadlines = {v.arch: v.slo_ms for v in traffic.placement_variants(args)}
    assert deadlines == {"pi0": 100.0, "xr0": 117.0}
    args.deadline = 0.0  # not given: the paper's
    assert {v.arch: v.slo_ms for v in traffic.placement_variants(args)} == {"pi0": 156.0, "xr0": 117.0}


def test_solver_speed_writes_only_the_file_it_is_given(tmp_path):
    """Its default --out was the committed bench/results/solver_speed.json, so a trial run replaced the recorded one."""
    committed = ROOT / "bench/results/solver_speed.json"
    before = committed.read_bytes()
    argv = [sys.executable, "bench/solver_speed.py", "--instances", "1", "--time-limit", "0.2"]
    res = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-1500:]
    assert "median_s" in res.stdout  # the table is printed either way
    assert committed.read_bytes() == before
    out = tmp_path / "speed.json"
    res = subprocess.run(argv + ["--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-1500:]
    import json

    doc = json.loads(out.read_text())
    assert doc["time_limit_s"] == 0.2 and doc["summary"]
    assert committed.read_bytes() == before
