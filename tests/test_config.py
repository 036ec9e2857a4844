import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from shared.config import ConfigError, config_from_dict, load_config

ROOT = Path(__file__).resolve().parent.parent


def base() -> dict:
    return {"models": [{"name": "a", "arch": "toy", "slo_ms": 100}, {"name": "b", "arch": "toy"}],
            "executors": [{"name": "e0", "models": ["a", "b"]}]}


def test_shipped_configs_load():
    from services.controlplane.planning import load_planning_file

    for path in (ROOT / "configs").glob("*.yaml"):
        if path.name.startswith("plan-"):  # planning files for `robion plan`
            load_planning_file(path)
        else:
            load_config(path)


def test_defaults():
    cfg = config_from_dict(base())
    assert cfg.engine.max_batch == 2 and cfg.engine.policy == "esf" and cfg.models[1].slo_ms == 156.0


@pytest.mark.parametrize("mutate,message", [
    (lambda d: d["models"][1].update(slo_ms=-5), "models[1].slo_ms: expected a positive number"),
    (lambda d: d["models"][1].update(slo_ms="fast"), "models[1].slo_ms: expected a number"),
    (lambda d: d["models"][1].update(hz=float("inf")), "models[1].hz: expected a positive number"),
    (lambda d: d["models"][0].update(slo_ms=float("nan")), "models[0].slo_ms: expected a positive number"),
    (lambda d: d["models"][0].update(robots=float("inf")), "models[0].robots: expected"),
    (lambda d: d["models"][0].update(colour="red"), "models[0].colour: unknown key"),
    (lambda d: d["models"][0].update(weights=""), "models[0].weights: expected a file path"),
    (lambda d: d["models"][1].update(tokenizer=" "), "models[1].tokenizer: expected a file path"),
    (lambda d: d["models"][0].update(arch="gpt5"), "models[0].arch: unknown architecture 'gpt5'"),
    (lambda d: d["models"][0].update(size="huge"), "models[0].size: toy has no size 'huge'"),
    (lambda d: d["models"][1].update(name="a"), "models[1].name: duplicate name 'a'"),
    (lambda d: d["executors"][0].update(models=["a", "zz"]), "executors[0].models[1]: no model named 'zz'"),
    (lambda d: d["executors"][0].update(device="tpu"), "executors[0].device: expected 'cpu' or 'cuda:N'"),
    (lambda d: d["executors"][0].update(models=["a"]), "models[1]: model 'b' is placed on no executor"),
    (lambda d: d.update(engine={"max_batch": 3}), "engine.max_batch: expected a power of two"),
    (lambda d: d.update(engine={"policy": "fifo"}), "engine.policy: expected one of esf, rr, lqf"),
    (lambda d: d.update(engine={"shed_expired": "yes"}), "engine.shed_expired: expected true or false"),
    (lambda d: d.update(control={"headroom": 0}), "control.headroom: expected a share in (0, 1]"),
    (lambda d: d.update(control={"headroom": 1.2}), "control.headroom: expected a share in (0, 1]"),
    (lambda d: d.update(router=[]), "router: expected a mapping"),
    (lambda d: d.pop("executors"), "executors: missing"),
    (lambda d: d.update(models="a"), "models: expected a list"),
    # a port above 65535 made prometheus' start_http_server raise OverflowError in the service
    (lambda d: d.update(router={"metrics_port": 70000}), "router.metrics_port: expected a port number"),
    (lambda d: d.update(control={"metrics_port": 65536}), "control.metrics_port: expected a port number"),
    (lambda d: d["executors"][0].update(metrics_port=99999), "executors[0].metrics_port: expected a port number"),
    # torch's manual_seed overflows above 2**64, numpy's default_rng refuses negative seeds: both crashed a
    # process later with a message that named no key
    (lambda d: d["models"][0].update(seed=2 ** 70), "models[0].seed: expected a non-negative integer"),
    (lambda d: d.update(engine={"seed": -1}), "engine.seed: expected a non-negative integer"),
    (lambda d: d.update(fleet={"seed": -3}), "fleet.seed: expected a non-negative integer"),
    (lambda d: d.update(control={"limits": {"seed": -1}}), "control.limits.seed: expected a non-negative integer"),
    # the planner reported this as "models.a.gpus: duplicate GPU index in [0, 0]", a path not in the file
    (lambda d: d["executors"][0].update(models=["a", "b", "a"]), "executors[0].models[2]: 'a' is listed twice"),
    # zmq refused these in the router / control plane with a ZMQError traceback
    (lambda d: d.update(router={"bind": "5555"}), "router.bind: expected an address like tcp://HOST:PORT"),
    (lambda d: d.update(router={"backend": "tcp://127.0.0.1"}), "router.backend: expected an address like"),
    (lambda d: d.update(router={"backend_connect": "tcp://router:70000"}), "router.backend_connect: expected"),
    (lambda d: d.update(control={"bind": "http://127.0.0.1:5557"}), "control.bind: expected an address like"),
    (lambda d: d.update(control={"connect": "tcp://control:port"}), "control.connect: expected an address"),
    # a bind's * host is no address to dial: `robion ctl` and every service ended in a ZMQError traceback
    (lambda d: d.update(control={"connect": "tcp://*:15557"}), "control.connect: expected an address to dial"),
    (lambda d: d.update(router={"backend_connect": "tcp://*:5556"}), "router.backend_connect: expected an address"),
    # str.isdigit passed these, and torch.device refused them in the executor (a traceback)
    (lambda d: d["executors"][0].update(device="cuda:01"), "executors[0].device: expected 'cpu' or 'cuda:N'"),
    (lambda d: d["executors"][0].update(device="cuda:\u00b2"), "executors[0].device: expected 'cpu' or 'cuda:N'"),
    # msgpack packs no integer from 2**64 on: every table_get and status of the control plane failed
    # without a reply (the routing table holds limits and quotas).
    (lambda d: d["models"][0].update(limit=2 ** 64), "models[0].limit: expected a positive integer below 2**63"),
    (lambda d: d["models"][0].update(robots=2 ** 64), "models[0].robots: expected a non-negative integer below 2**63"),
    (lambda d: d.update(engine={"max_queue": 2 ** 63}), "engine.max_queue: expected a positive integer below 2**63"),
    # past a float's range the checks raised OverflowError (a traceback, no key)
    (lambda d: d["models"][0].update(limit=10 ** 400), "models[0].limit: expected a positive integer below 2**63"),
    (lambda d: d["models"][0].update(robots=10 ** 400), "models[0].robots: expected a non-negative integer"),
    (lambda d: d["models"][0].update(slo_ms=10 ** 400), "models[0].slo_ms: expected a positive number"),
    (lambda d: d["models"][0].update(hz=-10 ** 400), "models[0].hz: expected a positive number"),
    (lambda d: d.update(control={"limits": {"target": 10 ** 400}}), "control.limits.target: expected a share"),
    # an executor's name is its ZeroMQ identity: the executor died binding its sockets (ZMQError traceback)
    (lambda d: d["executors"][0].update(name="x" * 256), "executors[0].name: expected at most 255 bytes"),
    (lambda d: d["executors"][0].update(name="é" * 128), "executors[0].name: expected at most 255 bytes"),
    (lambda d: d["executors"][0].update(name="\0ex"), "executors[0].name: a NUL character is not allowed"),
    # read as an option on the executor's command line: it never started, and nothing named the key
    (lambda d: d["executors"][0].update(name="-cpu1"), "executors[0].name: expected at most 255 bytes (UTF-8), not "
                                                       "starting with a zero byte or '-'"),
    # a file name with a NUL crashed its service at start-up (ValueError: embedded null byte)
    (lambda d: d.update(engine={"telemetry_file": "x\0a"}), "engine.telemetry_file: a NUL character is not allowed"),
    (lambda d: d.update(control={"state_dir": "st\0ate"}), "control.state_dir: a NUL character is not allowed"),
    # no upper bound: warm-up doubled the batch until the start timed out; every executor declared gone at once;
    # an OverflowError in the fleet after the whole cluster had started
    (lambda d: d.update(engine={"max_batch": 2 ** 40}), "engine.max_batch: expected a power of two (1, 2, 4, ...) "
                                                         "up to 256"),
    (lambda d: d.update(control={"heartbeat_s": 1e-6}), "control.heartbeat_s: expected a number of seconds, at least"),
    (lambda d: d.update(fleet={"robots": 3_000_000_000}), "fleet.robots: expected a positive integer up to 65536"),
    (lambda d: d.update(fleet={"hz": 1e12}), "fleet.hz: expected a positive number up to 1000"),
    # the second service to start failed to bind, as if another cluster held the address
    (lambda d: d.update(router={"bind": "tcp://127.0.0.1:5557"}), "control.bind: tcp://127.0.0.1:5557 is router.bind "
                                                                 "too"),
    # twice the limit overflowed a C long in the sockets' frame limit (OverflowError traceback)
    (lambda d: d.update(router={"max_message_bytes": 2 ** 62}), "router.max_message_bytes: expected a positive"),
    (lambda d: d.update(router={"keepalive_s": -1}), "router.keepalive_s: expected seconds from 0 (off)"),
    (lambda d: d.update(router={"keepalive_s": True}), "router.keepalive_s: expected a number"),
    (lambda d: d.update(router={"max_in_flight_per_robot": 0}), "router.max_in_flight_per_robot: expected a positive"),
    # the plane re-solves before answering a drain or apply, and `robion ctl` waits that long: a limit of 1e9 s
    # left the CLI an unusable timeout
    (lambda d: d.update(control={"solve_time_limit_s": 1e9}), "control.solve_time_limit_s: expected a positive number"),
    (lambda d: d.update(control={"solve_time_limit_s": 3600.5}), "control.solve_time_limit_s: expected a positive"),
    # the placement's byte count overflowed (int(inf): a traceback from `robion plan` and every service)
    (lambda d: d["executors"][0].update(memory_gb=1e300), "executors[0].memory_gb: expected a positive number"),
])
def test_errors_name_their_path(mutate, message):
    data = base()
    mutate(data)
    with pytest.raises(ConfigError) as e:
        config_from_dict(data)
    assert str(e.value).startswith(message), str(e.value)


def test_bad_files(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("models: [\n")
    with pytest.raises(ConfigError, match="not valid YAML at line"):
        load_config(bad)
    bad.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="config: expected a mapping"):
        load_config(bad)


def test_cli_reports_config_errors_without_traceback(tmp_path):
    data = base()
    data["models"][1]["slo_ms"] = 0
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(data))
    out = subprocess.run([sys.executable, "-m", "shared.cli", "up", "-c", str(path)], capture_output=True, text=True,
                         cwd=ROOT, timeout=60)
    assert out.returncode == 2
    assert "models[1].slo_ms: expected a positive number" in out.stderr
    assert "Traceback" not in out.stderr


def placed(placement, gpus=4):
    return {"gpus": gpus, "placement": placement,
            "models": [{"name": f"pi0-{i}", "arch": "toy", "seed": i} for i in range(2)]
            + [{"name": f"xr0-{i}", "arch": "toy2", "seed": i} for i in range(2)]}


def test_placement_shorthands(monkeypatch):
    from shared.config import _expand_placement

    mix = _expand_placement(placed("mix"))
    assert [e["device"] for e in mix["executors"]] == ["cuda:0", "cuda:1", "cuda:2", "cuda:3"]
    assert all(e["models"] == ["pi0-0", "pi0-1", "xr0-0", "xr0-1"] for e in mix["executors"])
    groups = _expand_placement(placed({"groups": {"toy": 1, "toy2": 3}}))
    assert [e["models"] for e in groups["executors"]] == [["pi0-0", "pi0-1"]] + [["xr0-0", "xr0-1"]] * 3
    listed = _expand_placement(placed({"groups": [{"arch": "toy", "gpus": [0, 2]}, {"arch": "toy2", "gpus": [1, 3]}]}))
    assert listed["executors"][2]["models"] == ["pi0-0", "pi0-1"]


@pytest.mark.parametrize("placement,message", [
    ({"groups": {"toy": 1, "toy2": 0}}, "placement.groups.toy2: expected a positive number of GPUs"),
    ({"groups": [{"arch": "toy", "gpus": []}, {"arch": "toy2", "gpus": [1]}]}, "placement.groups[0].gpus: the group is empty"),
    ({"groups": [{"arch": "ghost", "gpus": [0]}]}, "placement.groups[0].arch: no model of architecture 'ghost'"),
    ({"groups": [{"arch": "toy", "gpus": [0, 1]}, {"arch": "toy2", "gpus": [1, 2]}]}, "placement.groups[1].gpus: GPU 1 is already"),
    ({"groups": [{"arch": "toy", "gpus": [0, 9]}]}, "placement.groups[0].gpus: 9 is not a GPU index"),
    ({"groups": {"toy": 2}}, "placement.groups: no group serves ['xr0-0', 'xr0-1']"),
    ({"groups": {"toy": 1, "toy2": 1}}, "placement.groups: executors ['gpu2', 'gpu3'] are in no group"),
    ("spread", "placement: expected 'mix' or {groups: ...}"),
])
def test_placement_errors(placement, message):
    from shared.config import _expand_placement

    with pytest.raises(ConfigError) as e:
        _expand_placement(placed(placement))
    assert str(e.value).startswith(message), str(e.value)


def test_placement_must_fit_device_memory():
    from shared.placement import GIB, model_bytes

    # The estimate covers the peaks measured on the H100 (docs/RESULTS.md, model zoo: batch 4, with the
    # folded norm-weight copies that batches 1 and 2 made in the same process).
    for arch, peak_gib in (("pi0", 6.83), ("smolvla", 1.32), ("groot_n15", 4.98), ("xr0", 9.40)):
        assert peak_gib * GIB < model_bytes(arch, "full", 4) < 1.8 * peak_gib * GIB, arch  # conservative, not wasteful
    data = {"models": [{"name": "pi0", "arch": "pi0", "size": "full"}, {"name": "xr0", "arch": "xr0", "size": "full"}],
            "executors": [{"name": "g0", "device": "cuda:0", "models": ["pi0"], "memory_gb": 80},
                          {"name": "g1", "device": "cuda:1", "models": ["pi0", "xr0"], "memory_gb": 16}]}
    with pytest.raises(ConfigError) as e:
        config_from_dict(data)
    assert str(e.value).startswith("executors[1].models: the models placed on g1 need about 19.7 GiB")
    assert "but it has 16.0 GiB" in str(e.value)
    data["executors"][1]["memory_gb"] = 24
    config_from_dict(data)


@pytest.mark.parametrize("data,message", [
    # The reviewer's file: the groups shorthand copied model names before any check saw them (KeyError).
    ({"models": [{"arch": "toy"}], "gpus": 1, "placement": {"groups": {"toy": 1}}}, "models[0].name: missing"),
    ({"models": [{"arch": "toy"}], "gpus": 1, "placement": "mix"}, "models[0].name: missing"),
    ({"models": [{"name": 5, "arch": "toy"}], "gpus": 1, "placement": {"groups": {"toy": 1}}},
     "models[0].name: expected a string"),
    ({"models": [{"name": "a", "arch": "toy"}], "gpus": 1, "placement": {"groups": [{"arch": ["toy"], "gpus": [0]}]}},
     "placement.groups[0].arch: expected an architecture name"),
    # the model's arch, not the group's: it was "placement.groups[0].arch: no model of architecture 'toy'"
    ({"models": [{"name": "a", "arch": ["toy"]}], "gpus": 1, "placement": {"groups": {"toy": 1}}},
     "models[0].arch: expected a string"),
    ({"models": [{"name": "a", "arch": "toy"}], "gpus": 1, "placement": {"groups": {1: 1}}},
     "placement.groups.1: expected an architecture name"),
])
def test_placement_shorthand_mistakes_name_their_path(data, message):
    with pytest.raises(ConfigError) as e:
        config_from_dict(data)
    assert str(e.value).startswith(message), str(e.value)


def test_cli_reports_a_nameless_grouped_model_without_traceback(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("models:\n  - {arch: toy}\ngpus: 1\nplacement: {groups: {toy: 1}}\n")
    out = subprocess.run([sys.executable, "-m", "shared.cli", "up", "-c", str(path)], capture_output=True, text=True,
                         cwd=ROOT, timeout=60)
    assert out.returncode == 2, out.stderr
    assert "models[0].name: missing" in out.stderr and "Traceback" not in out.stderr


@pytest.mark.parametrize("text, message", [
    # yaml.safe_load kept the last value of a repeated key: robots 9 was planned where 2 was written first
    ("models:\n  - {name: a, arch: toy, robots: 2, limit: 4, robots: 9}\nexecutors:\n  - {name: e0, models: [a]}\n",
     "duplicate key 'robots' at line 2, column 47 (first given at line 2, column 26)"),
    ("models:\n  - {name: a, arch: toy}\nexecutors:\n  - {name: e0, models: [a]}\n"
     "control: {headroom: 0.5}\ncontrol: {strategy: smg}\n",
     "duplicate key 'control' at line 6, column 1 (first given at line 5, column 1)"),
    ("models:\n  - name: a\n    arch: toy\n    name: b\nexecutors:\n  - {name: e0, models: [a]}\n",
     "duplicate key 'name' at line 4"),
])
def test_duplicate_keys_are_refused(tmp_path, text, message):
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_config(path)
    assert str(e.value).startswith(f"{path}: {message}"), str(e.value)


def test_merge_keys_may_still_override():
    """A key a merge (`<<: *base`) brings in is not a duplicate: overriding it is what merges are for."""
    from shared.config import config_from_text

    cfg = config_from_text("models:\n  - &a {name: a, arch: toy, slo_ms: 100}\n  - {<<: *a, name: b, slo_ms: 50}\n"
                           "executors:\n  - {name: e0, models: [a, b]}\n")
    assert [(m.name, m.slo_ms) for m in cfg.models] == [("a", 100.0), ("b", 50.0)]


def test_the_gpus_shorthand_is_capped_before_it_builds_executors():
    from shared.config import MAX_EXECUTORS, _expand_placement

    with pytest.raises(ConfigError, match=f"gpus: at most {MAX_EXECUTORS} executors in one cluster, got 100000000"):
        _expand_placement(placed("mix", gpus=100_000_000))
    assert len(_expand_placement(placed("mix", gpus=MAX_EXECUTORS))["executors"]) == MAX_EXECUTORS
    # A list of executors is capped too: the planner refused it at every solve, naming `gpus`, a key not in the file.
    data = base()
    data["executors"] = [{"name": f"e{j}", "models": ["a", "b"]} for j in range(MAX_EXECUTORS + 1)]
    with pytest.raises(ConfigError, match=f"executors: at most {MAX_EXECUTORS} executors in one cluster, got 4097"):
        config_from_dict(data)
    # gpus: N alone lists no models on its GPUs; the error named executors[0].models, a path not in the file.
    with pytest.raises(ConfigError, match="placement: gpus: N needs placement: mix"):
        config_from_dict({"models": base()["models"], "gpus": 2})


def test_device_lists_take_ascii_indices_only():
    from shared.config import parse_devices

    assert parse_devices("0+1") == ["cuda:0", "cuda:1"] and parse_devices("cuda:3, cpu") == ["cuda:3", "cpu"]
    for bad in ("\u00b2", "cuda:01", "01"):
        with pytest.raises(ValueError, match="is not a device"):
            parse_devices(bad)


def test_peers_dial_a_wildcard_bind_on_loopback():
    from shared.config import dial_address

    assert dial_address("tcp://*:5555") == "tcp://127.0.0.1:5555"
    assert dial_address("tcp://0.0.0.0:5555") == "tcp://127.0.0.1:5555"
    assert dial_address("tcp://[::]:5555") == "tcp://[::1]:5555"
    assert dial_address("tcp://[::]:5555", "tcp://host:1") == "tcp://host:1"
