"""Config values that used to load and then crash a service at start-up (a traceback without the key), or
that gave an error naming a path the file does not have: each is now refused when the config loads."""

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from shared.config import ConfigError, config_from_dict
from tests.helpers import cluster_config
from tests.test_config import base

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize("address", ["tcp://127.0.0.1:5555", "tcp://*:5555", "tcp://0.0.0.0:1", "tcp://router:65535",
                                     "tcp://[::1]:5555", "ipc:///tmp/robion.sock"])
def test_addresses_zmq_takes_still_load(address):
    data = base()
    data["router"] = {"bind": address}
    assert config_from_dict(data).router.bind == address


@pytest.mark.parametrize("key", [("router", "bind"), ("router", "backend"), ("control", "bind"), ("control", "connect")])
def test_an_inproc_address_is_refused_naming_the_key(key):
    """inproc:// joins sockets of one process; the services are processes of their own. A cluster configured with it
    passed the checks and then never became ready (`robion up` waited out its timeout, 300 s by default)."""
    data = base()
    data[key[0]] = {key[1]: "inproc://router"}
    with pytest.raises(ConfigError) as e:
        config_from_dict(data)
    assert str(e.value).startswith(f"{key[0]}.{key[1]}: expected an address"), str(e.value)
    assert "not inproc://" in str(e.value) or "ipc://PATH" in str(e.value), str(e.value)


def test_a_model_arch_that_is_not_a_string_is_named_in_placement_groups():
    # Used to raise TypeError (unhashable list) while listing the models no group serves.
    data = {"models": [{"name": "a", "arch": "toy"}, {"name": "b", "arch": ["toy"]}], "gpus": 1,
            "placement": {"groups": [{"arch": "toy", "gpus": [0]}]}}
    with pytest.raises(ConfigError) as e:
        config_from_dict(data)
    assert str(e.value).startswith("models[1].arch: expected a string"), str(e.value)


def test_a_metrics_port_out_of_range_stops_robion_up_with_the_key(tmp_path):
    path, data = cluster_config(tmp_path)
    data["router"]["metrics_port"] = 70000
    path.write_text(yaml.safe_dump(data))
    out = subprocess.run([sys.executable, "-m", "shared.cli", "up", "-c", str(path)], capture_output=True, text=True,
                         cwd=ROOT, timeout=120)
    assert out.returncode == 2, out.stderr
    assert "router.metrics_port: expected a port number" in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_serve_logs_a_port_out_of_range_instead_of_raising(caplog):
    # An executor's --metrics-port bypasses the config check; a bad one must not kill the service.
    from prometheus_client import CollectorRegistry

    from shared.metrics import serve

    assert serve(CollectorRegistry(), 70000) is False
    assert "cannot serve metrics on port 70000" in caplog.text


def test_largest_integers_the_wire_carries_still_load():
    data = base()
    data["models"][0].update(limit=2 ** 63 - 1, robots=2 ** 63 - 1)
    cfg = config_from_dict(data)
    assert cfg.models[0].limit == 2 ** 63 - 1 and cfg.models[0].robots == 2 ** 63 - 1
