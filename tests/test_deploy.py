"""docker-compose.yml against the code it starts: each service's command names a real entry
point with options it accepts, the config it names loads, and the addresses in that config
point at the compose services. (The containers themselves need a Docker daemon; the same
processes run on loopback in test_cluster.py.)"""

from __future__ import annotations

import importlib
import re
import shlex
from pathlib import Path
from urllib.parse import urlparse

import pytest
import yaml

from shared.config import load_config
from shared.service import service_args

ROOT = Path(__file__).resolve().parent.parent
COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
SERVICES = COMPOSE["services"]


def python_argv(service: dict) -> list[str]:
    """The ``python -m module ...`` argv of a compose command, with ``$${VAR}`` (compose escapes) replaced by the
    values a container would give them (Docker sets HOSTNAME in every container)."""
    cmd = service["command"]
    if cmd.startswith("sh -c "):
        cmd = shlex.split(cmd)[2]
        # The image's sh (dash) does not exec its last command: it stays PID 1, which ignores docker's SIGTERM, so
        # the service never drained and was killed at the end of its stop grace. The command must exec python.
        assert cmd.startswith("exec python "), f"{service['command']!r}: a shell-wrapped command must exec python"
        cmd = cmd[len("exec "):]
        # Compose fills ${VAR:-default} from the host's environment: unset there, the default.
        env = {"HOSTNAME": "replica-1", **{k: re.sub(r"\$\{\w+:-([^}]*)\}", r"\1", v)
                                           for k, v in service.get("environment", {}).items()}}
        for key, value in env.items():
            cmd = cmd.replace(f"$${{{key}}}", value)
    argv = shlex.split(cmd)
    assert argv[:2] == ["python", "-m"], f"{service['command']!r} is not a python -m command"
    return argv[2:]


@pytest.mark.parametrize("name", sorted(SERVICES))
def test_compose_command_is_a_real_entry_point(name):
    module, *args = python_argv(SERVICES[name])
    mod = importlib.import_module(module)
    assert callable(getattr(mod, "main", None)), f"{module} has no main()"
    service = module.split(".")[1]
    extra = None
    if service == "executor":
        from services.executor.main import _args as extra
    parsed = service_args(service, args, extra)  # exits (SystemExit) on an option the service does not take
    cfg = load_config(ROOT / parsed.config)
    if service == "executor":
        names = {e.name for e in cfg.executors}
        models = {m.name for m in cfg.models}
        # A named executor is in the config; a replica brings models the config defines.
        assert parsed.name in names or (parsed.models and set(parsed.models.split(",")) <= models), parsed


def test_every_service_runs_under_an_init_and_executors_have_time_to_drain():
    """init: Python as PID 1 ignores a SIGTERM that comes before its handler is installed, so a stop right after a start
    waited out the stop grace and killed a process serving by then. An executor's drain is bounded by ExecutorIO's
    WITHDRAW_* waits, plus a few seconds to close and exit: the grace must cover them, or it is killed mid-drain."""
    from services.executor.transport import ExecutorIO as IO

    drain_s = IO.WITHDRAW_SOLVE_S + IO.WITHDRAW_REPLY_S + IO.WITHDRAW_ACK_S + IO.WITHDRAW_ANSWER_S + 5
    for name, service in SERVICES.items():
        assert service.get("init") is True, name
        if python_argv(service)[0] == "services.executor.main":
            grace = service.get("stop_grace_period", "10s")
            assert grace.endswith("s") and float(grace[:-1]) >= drain_s, (name, grace, drain_s)
            # The SM profiles and robot limits outlive the container: a new replica on a GPU otherwise profiles anew.
            assert "robion-state:/app/state" in service.get("volumes", []), name
    assert "robion-state" in COMPOSE["volumes"]


def test_compose_addresses_point_at_compose_services():
    argvs = [python_argv(s) for s in SERVICES.values()]
    configs = {argv[argv.index("-c") + 1] for argv in argvs}
    assert len(configs) == 1, f"services read different configs: {configs}"
    cfg = load_config(ROOT / configs.pop())
    dialled = [urlparse(cfg.router.backend_connect), urlparse(cfg.control.connect)]
    hosts = {url.hostname: url.port for url in dialled}
    binds = {"router": urlparse(cfg.router.backend.replace("*", "0.0.0.0")).port,
             "control": urlparse(cfg.control.bind.replace("*", "0.0.0.0")).port}
    for host, port in hosts.items():
        assert host in SERVICES, f"{host} is not a compose service"
        assert binds[host] == port, f"{host} binds {binds[host]}, the others dial {port}"
    published = [p.split(":") for p in SERVICES["router"].get("ports", [])]
    robot_port = urlparse(cfg.router.bind.replace("*", "0.0.0.0")).port
    assert [str(robot_port)] * 2 in published, f"the robots' port {robot_port} is not published: {published}"
    for name, service in SERVICES.items():
        assert set(service.get("depends_on", [])) <= set(SERVICES), name
        assert service["build"]["dockerfile"] == "deploy/Dockerfile" and (ROOT / "deploy/Dockerfile").exists()


def test_prometheus_scrapes_every_compose_service_on_its_metrics_port():
    """deploy/prometheus.yml reaches each service's /metrics, scaled-out executor replicas included (they
    have no fixed host names: the compose service name resolves to all of them)."""
    from services.executor.main import _args as executor_args

    prom = yaml.safe_load((ROOT / "deploy" / "prometheus.yml").read_text())
    scraped = set()
    for job in prom["scrape_configs"]:
        for static in job.get("static_configs", []):
            scraped |= set(static["targets"])
        for dns in job.get("dns_sd_configs", []):
            scraped |= {f"{name}:{dns['port']}" for name in dns["names"]}
    wanted = set()
    for name, service in SERVICES.items():
        module, *args = python_argv(service)
        kind = module.split(".")[1]
        parsed = service_args(kind, args, executor_args if kind == "executor" else None)
        cfg = load_config(ROOT / parsed.config)
        if kind == "router":
            port = cfg.router.metrics_port
        elif kind == "controlplane":
            port = cfg.control.metrics_port
        else:  # as services/executor/main.py picks it: --metrics-port, else the config's, else 9110 + index
            index = next((i for i, e in enumerate(cfg.executors) if e.name == parsed.name), 0)
            ex = next((e for e in cfg.executors if e.name == parsed.name), None)
            port = parsed.metrics_port if parsed.metrics_port is not None else (
                ex.metrics_port_or_default(index) if ex else 9110 + index)
        if port:
            wanted.add(f"{name}:{port}")
    assert wanted <= scraped, f"not scraped: {sorted(wanted - scraped)}"
