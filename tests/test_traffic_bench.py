"""The multi-GPU experiment driver on the CPU with tiny models: assignments per strategy and placement."""

import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FAST = ["--size", "tiny", "--gpus", "2", "--devices", "cpu", "--engine", "monolithic", "--epochs", "1",
        "--duration", "1.5", "--limit-epochs", "1", "--limit-duration", "1", "--max-robots", "4"]


def run(tmp_path, *args):
    out = tmp_path / "r.json"
    res = subprocess.run([sys.executable, "bench/traffic.py", *args, *FAST, "--out", str(out)], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    return json.loads(out.read_text())


def test_strategies_experiment(tmp_path):
    r = run(tmp_path, "strategies", "--arch", "pi0")
    rows = {row["label"]: row for row in r["rows"]}
    assert set(rows) == {"smg", "eps", "ip"}
    robots = {v["name"]: v["robots"] for v in r["variants"]}
    assert [v["hz"] for v in r["variants"]] == [1, 2, 2, 4]
    for row in rows.values():
        assert {m: sum(per.values()) for m, per in row["assignment"].items()} == robots
        assert row["sent"] > 0 and 0 <= row["misses"] <= row["sent"]
    assert all(len(per) == 1 for per in rows["smg"]["assignment"].values())  # one GPU per model
    assert all(len(per) == 2 for per in rows["eps"]["assignment"].values())  # split over both
    assert rows["ip"]["feasible"]


def test_placements_experiment(tmp_path):
    # One robot per variant (4 pi0 and 4 XR0 variants): with fewer, the XR0 variants got no robots and their
    # side of the group check held whatever the placement.
    r = run(tmp_path, "placements", "--arch", "pi0", "--arch2", "xr0", "--robots", "8")
    labels = [row["label"] for row in r["rows"]]
    assert labels == ["mix", "gr-1:1"]
    group = r["rows"][1]["assignment"]
    assert len(group) == 8 and all(sum(per.values()) >= 1 for per in group.values()), group
    assert all(set(per) == ({"0"} if m.startswith("pi0") else {"1"}) for m, per in group.items()), group


def test_limits_from_cache_file_set_equal_populations(tmp_path):
    """Cached limits are used as they are (nothing measured); equal robot shares at 1/2/2/4 Hz
    ask for load x GPUs GPU-equivalents in all."""
    cache = tmp_path / "limits.json"
    limits = {1: 12, 2: 6, 4: 3}
    cache.write_text(json.dumps({f"cpu|pi0:tiny|{hz}Hz|mb2|156ms|monolithic|at0.98": {"limit": c}
                                 for hz, c in limits.items()}))
    out = tmp_path / "r.json"
    res = subprocess.run([sys.executable, "bench/traffic.py", "strategies", "--arch", "pi0", *FAST, "--load", "3",
                          "--limits-cache", str(cache), "--out", str(out)], cwd=ROOT, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "measuring" not in res.stdout
    variants = json.loads(out.read_text())["variants"]
    assert [v["limit"] for v in variants] == [12, 6, 6, 3]
    # 3 x 2 GPUs = N (1/12 + 2/6 + 1/3) GPU-equivalents: N = 8 robots of each variant
    assert [v["robots"] for v in variants] == [8, 8, 8, 8]


def test_limits_experiment_measures_each_rate_once(tmp_path):
    cache = tmp_path / "limits.json"
    res = subprocess.run([sys.executable, "bench/traffic.py", "limits", "--arch", "pi0", "--arch2", "xr0",
                          "--rates", "1,2,4", "--hz", "2", *FAST, "--devices", "cpu,cpu", "--limits-cache", str(cache)],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "measuring 4 robot limits on 2 device(s)" in res.stdout  # pi0 at 2 Hz is measured once
    keys = sorted(json.loads(cache.read_text()))
    assert keys == sorted(f"cpu|{a}:tiny|{hz}Hz|mb2|{d}ms|monolithic|at0.98"
                          for a, hz, d in [("pi0", 1, 156), ("pi0", 2, 156), ("pi0", 4, 156), ("xr0", 2, 117)])
    assert all(1 <= e["limit"] <= 4 for e in json.loads(cache.read_text()).values())


def probe(tag, device):
    return tag, device, os.getpid()


def fail(tag, device):
    raise ValueError(f"job {tag} failed on {device}")


def test_device_pool_routes_by_slot_keeps_order_and_raises():
    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import traffic

    pool = traffic.DevicePool(["dev-a", "dev-b"])  # device names are passed through to the calls
    try:
        out = pool.run([(i, probe, (i,)) for i in range(5)])
        assert [o[0] for o in out] == [0, 1, 2, 3, 4]
        assert [o[1] for o in out] == ["dev-a", "dev-b", "dev-a", "dev-b", "dev-a"]
        workers = {device: {pid for _, d, pid in out if d == device} for device in ("dev-a", "dev-b")}
        assert all(len(p) == 1 for p in workers.values())  # one worker process per device, kept
        assert workers["dev-a"] != workers["dev-b"] and os.getpid() not in workers["dev-a"] | workers["dev-b"]
        with pytest.raises(ValueError, match="job 1 failed on dev-b"):
            pool.run([(0, probe, (0,)), (1, fail, (1,))])
        assert pool.run([(3, probe, (7,))])[0][:2] == (7, "dev-b")  # the pool survives a failed call
    finally:
        pool.close()
