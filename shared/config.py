"""Cluster configuration: YAML -> validated dataclasses.

Every mistake is reported with its path (``models[1].slo_ms: expected a positive number``)
as a ConfigError, never as a traceback, and every key the file may hold is declared here.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
import math
import re
import sys
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml


class ConfigError(ValueError):
    """A configuration mistake; ``str(err)`` is the message to show the operator."""


class DuplicateKeyError(yaml.constructor.ConstructorError):
    """A mapping that gives one key twice. PyYAML keeps the last value without a word, so a
    repeated `robots:` or model name would silently replace the first; every file is refused instead."""

    def __init__(self, key: Any, mark: yaml.Mark, first: yaml.Mark) -> None:
        super().__init__(None, None, f"duplicate key {key!r}", mark)
        self.key = key
        self.line, self.column = mark.line + 1, mark.column + 1
        self.first_line, self.first_column = first.line + 1, first.column + 1

    def __str__(self) -> str:
        return (f"duplicate key {self.key!r} at line {self.line}, column {self.column} "
                f"(first given at line {self.first_line}, column {self.first_column})")


class UniqueKeyLoader(yaml.SafeLoader):
    """yaml.SafeLoader that raises DuplicateKeyError on a key given twice in one mapping.

    Keys a merge (``<<: *base``) brings in may still be overridden: that is what merges are for."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, yaml.Mark] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.setdefault(key, key_node.start_mark)
                except TypeError:  # an unhashable key: SafeLoader reports it itself
                    continue
                if first is not key_node.start_mark:
                    raise DuplicateKeyError(key, key_node.start_mark, first)
        return super().construct_mapping(node, deep=deep)


def load_yaml(text: str) -> Any:
    """Parse YAML text like yaml.safe_load, but refuse a mapping key given twice (DuplicateKeyError,
    a yaml.YAMLError). Every file the operator writes is read through this."""
    return yaml.load(text, Loader=UniqueKeyLoader)


def positive_number(v: Any) -> bool:
    """A finite number above zero: the check of every rate, size, count and timeout setting
    (``.inf`` / ``.nan`` parse as floats from YAML, and no rate or size is infinite). An int is
    always finite; math.isfinite would raise OverflowError past a float's range."""
    return (isinstance(v, int) or math.isfinite(v)) and v > 0


def _non_negative(v: Any) -> bool:
    return (isinstance(v, int) or math.isfinite(v)) and v >= 0


# Integers a setting may hold: what msgpack (the control messages, which carry robot limits and
# populations in the routing table) and other languages' clients read as int64. Past it
# every table_get and status of the control plane would fail to pack.
INT_MIN, INT_MAX = -(2 ** 63), 2 ** 63 - 1


def _power_of_two(v: Any) -> bool:
    return v >= 1 and v & (v - 1) == 0


# Upper bounds where a bigger value only ever meant a mistake, and went on to a hang or a crash: an engine warms up
# and captures every power-of-two batch up to max_batch (2^40 never became ready), a heartbeat of a microsecond had
# every executor declared gone, and a fleet of 2^31 robots overflowed ZeroMQ's socket count.
MAX_BATCH = 256
MIN_HEARTBEAT_S = 0.01
FLEET_MAX_ROBOTS = 65536
FLEET_MAX_HZ = 1000.0  # per robot; a period under the clock's resolution never advanced a robot's next send


def _port(v: Any) -> bool:
    """A TCP port, or 0 (disabled): above 65535 the socket's bind raises OverflowError in the service."""
    return 0 <= v <= 65535


def _seed(v: Any) -> bool:
    """What every seed is handed to: torch's manual_seed (overflows above 2**64) and numpy's default_rng
    (refuses negatives). Checked here, so the error names the key instead of crashing a process later."""
    return 0 <= v < 2 ** 63


# No inproc://: it joins sockets of one process, and the router, control plane, executors and fleet are processes of
# their own (a cluster configured with it never became ready, and said nothing of why).
_ADDRESS_RE = re.compile(r"(tcp://(\*|\[[0-9A-Fa-f:.]+\]|[^:/\[\]\s]+):(\d+)|ipc://\S+)")


# An executor's memory_gb at most (a petabyte): 1e300 overflowed the placement's byte count (a traceback).
MAX_MEMORY_GB = 1_000_000

# The traffic solve blocks every drain, resume and apply answer (and `robion ctl` waits that long): an hour is
# far past any useful solve, and a bound keeps those waits something an operator can sit through.
MAX_SOLVE_TIME_LIMIT_S = 3600


def solve_time_limit(v: Any) -> bool:
    """control.solve_time_limit_s: a positive number of seconds, at most MAX_SOLVE_TIME_LIMIT_S."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and positive_number(v) and v <= MAX_SOLVE_TIME_LIMIT_S


def valid_address(v: Any) -> bool:
    """A ZeroMQ endpoint the services can bind or dial: tcp://HOST:PORT (HOST may be * in a bind) or ipc://PATH.
    zmq refuses anything else with a bare "Invalid argument" at start-up."""
    m = _ADDRESS_RE.fullmatch(v)
    return bool(m) and (m.group(3) is None or 1 <= int(m.group(3)) <= 65535)


def valid_dial_address(v: Any) -> bool:
    """An address to dial: as valid_address, but no * host, which only a bind takes (zmq refuses to dial it)."""
    return valid_address(v) and not v.startswith("tcp://*:")


_DEVICE_RE = re.compile(r"cpu|cuda:(0|[1-9][0-9]*)")


def valid_device(v: str) -> bool:
    """'cpu' or 'cuda:N' in ASCII digits without a leading zero, as torch.device takes it (str.isdigit also
    passed 'cuda:01' and 'cuda:²', which torch refuses with a traceback)."""
    return bool(_DEVICE_RE.fullmatch(v))


def _check(pred, text: str) -> dict[str, Any]:
    return {"check": (pred, text)}


_ADDRESS = _check(valid_address, "expected an address like tcp://HOST:PORT or ipc://PATH (not inproc://: the services "
                                 "are separate processes)")
_DIAL = _check(valid_dial_address, "expected an address to dial like tcp://HOST:PORT (no * host) or ipc://PATH")
_SEED = _check(_seed, "expected a non-negative integer below 2**63")
# Most executors one cluster config describes: the traffic controller plans at most that many GPUs
# (services/controlplane/solver.py, MAX_GPUS), and `gpus: N` must not build a list of any size first.
MAX_EXECUTORS = 4096
MAX_EXECUTOR_NAME_BYTES = 255  # a ZeroMQ socket identity's limit (executors are routed by name)
MAX_MESSAGE_LIMIT = 1 << 32  # router.max_message_bytes at most (4 GiB)
# An empty path would read as "no file" further on: random weights or byte ids served where a file was meant.
_FILE = _check(lambda v: v.strip() != "", "expected a file path (leave the key out for none)")


@dataclass
class ModelConfig:
    name: str
    arch: str
    size: str = "tiny"  # "tiny" for CPU demos and tests, "full" for the published dimensions
    # seeded random weights; another seed is another fine-tuned variant
    seed: int = field(default=0, metadata=_SEED)
    weights: str | None = field(default=None, metadata=_FILE)  # safetensors file of the model's own state dict
    tokenizer: str | None = field(default=None, metadata=_FILE)  # tokenizer file; a byte-level tokenizer when absent
    slo_ms: float = field(default=156.0, metadata=_check(positive_number, "expected a positive number"))
    robots: int = field(default=0, metadata=_check(_non_negative, "expected a non-negative integer"))  # population N_i
    # request rate per robot
    hz: float = field(default=2.0, metadata=_check(positive_number, "expected a positive number"))
    limit: int | None = field(default=None, metadata=_check(positive_number, "expected a positive integer"))
    # limit = C_i, robots of this model one GPU sustains at the target SLO attainment (measured when absent)


# Model settings only the traffic controller reads: executors never use a population, and a configured limit
# only tells them not to measure one. (An apply that removes a limit leaves the model unplanned until an executor
# measures it at its next start, as for a model added without one.)
TRAFFIC_ONLY_MODEL_FIELDS = frozenset({"robots", "limit"})


def executor_settings(model: ModelConfig) -> dict[str, Any]:
    """The settings of a model its executor loads or serves by: all but those only the traffic controller reads."""
    return {k: v for k, v in dataclasses.asdict(model).items() if k not in TRAFFIC_ONLY_MODEL_FIELDS}


def settings_digest(model: ModelConfig) -> str:
    """A short fingerprint of ``executor_settings``: an executor registers one per model it serves, so the
    control plane can tell whether it runs what the desired state says."""
    text = json.dumps(executor_settings(model), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass
class ExecutorConfig:
    name: str
    models: list[str]
    device: str = "cpu"  # "cpu" or "cuda:N"
    memory_gb: float | None = field(default=None, metadata=_check(
        lambda v: positive_number(v) and v <= MAX_MEMORY_GB, f"expected a positive number of GiB, at most {MAX_MEMORY_GB}"))
    # device memory to plan with; checked against the models' estimated needs (see shared/placement.py)
    metrics_port: int | None = field(default=None, metadata=_check(_port, "expected a port number 0-65535 (0 disables)"))
    # None: 9110 + the executor's position in this list

    def metrics_port_or_default(self, index: int) -> int:
        return 9110 + index if self.metrics_port is None else self.metrics_port


@dataclass
class EngineConfig:
    # which engine runs the stages: a key of ENGINES in services/executor/engine.py, or auto (robion on a GPU,
    # monolithic on the CPU: services/executor/engine.resolve_kind)
    kind: str = "auto"
    max_batch: int = field(default=2, metadata=_check(lambda v: _power_of_two(v) and v <= MAX_BATCH,
                                                      f"expected a power of two (1, 2, 4, ...) up to {MAX_BATCH}"))
    policy: str = "esf"  # esf (earliest-SLO-first), rr (round-robin), lqf (largest-queue-first)
    max_queue: int = field(default=256, metadata=_check(positive_number, "expected a positive integer"))
    shed_expired: bool = True  # answer DEADLINE_EXCEEDED instead of running requests already late
    # also those whose deadline is nearer than their model's recent service time (p90): overload control
    shed_late: bool = False
    seed: int = field(default=0, metadata=_SEED)  # noise generator seed
    # Lockstep engines (robion and its comparison engines):
    sm_policy: str = "table"  # VLM SM restriction: table (profiled per stage pair), none, static
    static_sms: int = field(default=0, metadata=_check(_non_negative, "expected a non-negative integer"))
    sm_table: str | None = None  # SM table JSON to use (profiled and written there when missing)
    profile_dir: str = "state/profiles"  # where SM tables are cached when sm_table is not given
    profile_repeats: int = field(default=5, metadata=_check(positive_number, "expected a positive integer"))
    graphs: bool = True  # CUDA graphs per (model, stage, batch, SM level); false: eager stages (debugging)
    telemetry_file: str | None = None  # append one JSON line per lockstep
    # Comparison engines (services/executor/baselines, docs/baselines.md):
    disjoint_sms: int = field(default=0, metadata=_check(_non_negative, "expected a non-negative integer"))
    # disjoint: SMs of the VLM partition (a multiple of 8); 0: profiled at start-up and cached in profile_dir
    running_batch: int = field(default=0, metadata=_check(_non_negative, "expected a non-negative integer"))
    # procdisagg: most requests in the action process's running batch; 0: 4 x max_batch
    handoff_slots: int = field(default=4, metadata=_check(positive_number, "expected a positive integer"))
    # procdisagg: groups of max_batch handoff slots per model in the inter-stage buffer
    procdisagg_workers: str = "process"  # procdisagg: stages as "process"es (CUDA IPC) or "thread"s (debugging)
    # interdisagg (both required there): the devices of its VLM workers and of its action workers,
    # one worker per entry: "cuda:0,cuda:1", or indices "0,1" = cuda:0,cuda:1; "+" separates too,
    # so a list fits in bench/capacity.py --engines, where "," and ":" are taken; "cpu" on a CPU.
    vlm_devices: str = ""
    action_devices: str = ""


@dataclass
class RouterConfig:
    bind: str = field(default="tcp://127.0.0.1:5555", metadata=_ADDRESS)  # robots connect here (DEALER)
    backend: str = field(default="tcp://127.0.0.1:5556", metadata=_ADDRESS)  # executors connect here (DEALER)
    backend_connect: str | None = field(default=None, metadata=_DIAL)
    # address executors dial when it differs from the bind (containers)
    # Capped: the sockets' frame limit is twice this (plus headers) in a C long.
    max_message_bytes: int = field(default=16 * 1024 * 1024, metadata=_check(
        lambda v: positive_number(v) and v <= MAX_MESSAGE_LIMIT, "expected a positive integer up to 4 GiB (2**32)"))
    request_timeout_s: float = field(default=30.0, metadata=_check(positive_number, "expected a positive number"))
    # Requests one robot connection may have in flight; beyond it that robot's requests are answered OVERLOADED at
    # once. A robot calling a few times a second has one or two; a runaway client loop would otherwise fill its
    # model's executor queues and starve every other robot of that model.
    max_in_flight_per_robot: int = field(default=64, metadata=_check(positive_number, "expected a positive integer"))
    # Heartbeats between router and executors: a connection silent this long after a ping is closed (a frozen
    # executor or router, a dead host, a name taken by another connection); pings go every third of it. 0: none.
    # Raise it where one request takes seconds to cross the link: a ping waits behind the data before it.
    keepalive_s: float = field(default=3.0, metadata=_check(lambda v: 0 <= v <= 3600, "expected seconds from 0 (off) "
                                                                                   "to 3600"))
    metrics_port: int = field(default=9100, metadata=_check(_port, "expected a port number 0-65535 (0 disables)"))


@dataclass
class LimitsConfig:
    """How executors measure robot limits C_i for models whose config gives none."""

    auto: bool = False  # measure at executor start-up (cached in control.state_dir/limits.json)
    target: float = field(default=0.98, metadata=_check(lambda v: 0 < v <= 1, "expected a share in (0, 1]"))
    epochs: int = field(default=5, metadata=_check(positive_number, "expected a positive integer"))
    duration_s: float = field(default=10.0, metadata=_check(positive_number, "expected a positive number"))
    max_robots: int = field(default=256, metadata=_check(positive_number, "expected a positive integer"))
    seed: int = field(default=0, metadata=_SEED)
    network: str = "wifi7"
    progress: bool = True


@dataclass
class ControlConfig:
    bind: str = field(default="tcp://127.0.0.1:5557", metadata=_ADDRESS)
    connect: str | None = field(default=None, metadata=_DIAL)
    # address other services dial when it differs from the bind (containers)
    heartbeat_s: float = field(default=0.5, metadata=_check(lambda v: positive_number(v) and v >= MIN_HEARTBEAT_S,
                                                            f"expected a number of seconds, at least {MIN_HEARTBEAT_S}"))
    missed_heartbeats: int = field(default=6, metadata=_check(positive_number, "expected a positive integer"))
    state_dir: str = "state"
    metrics_port: int = field(default=9101, metadata=_check(_port, "expected a port number 0-65535 (0 disables)"))
    strategy: str = "ip"  # robot-to-GPU assignment: ip (integer program), smg, eps, none (round-robin per request)
    solve_time_limit_s: float = field(default=5.0, metadata=_check(
        solve_time_limit, f"expected a positive number of seconds, at most {MAX_SOLVE_TIME_LIMIT_S}"))
    # Share of each robot limit C_i the traffic controller fills (floor(C_i * headroom)); below 1
    # keeps slack under the measured limit, where SLO attainment falls off steeply.
    headroom: float = field(default=1.0, metadata=_check(lambda v: 0 < v <= 1, "expected a share in (0, 1]"))
    limits: LimitsConfig = field(default_factory=LimitsConfig)


@dataclass
class FleetConfig:
    """The simulated fleet `robion demo` drives."""

    robots: int = field(default=8, metadata=_check(lambda v: positive_number(v) and v <= FLEET_MAX_ROBOTS,
                                                   f"expected a positive integer up to {FLEET_MAX_ROBOTS}"))
    hz: float = field(default=2.0, metadata=_check(lambda v: positive_number(v) and v <= FLEET_MAX_HZ,
                                                   f"expected a positive number up to {FLEET_MAX_HZ:g}"))
    duration_s: float = field(default=10.0, metadata=_check(positive_number, "expected a positive number"))
    seed: int = field(default=0, metadata=_SEED)
    network: str = "wifi7"
    models: list[str] | None = None  # models the robots use, round-robin; all models when absent


@dataclass
class ClusterConfig:
    models: list[ModelConfig]
    executors: list[ExecutorConfig]
    # Python modules imported before the models are checked, each registering architectures of its own with
    # @register (docs/models.md, "Serving your own two-stage VLA"); the config file's folder is searched too.
    imports: list[str] = field(default_factory=list)
    engine: EngineConfig = field(default_factory=EngineConfig)
    router: RouterConfig = field(default_factory=RouterConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    fleet: FleetConfig = field(default_factory=FleetConfig)

    def model(self, name: str) -> ModelConfig:
        for m in self.models:
            if m.name == name:
                return m
        raise KeyError(name)

    def executor(self, name: str) -> ExecutorConfig:
        for e in self.executors:
            if e.name == name:
                return e
        raise KeyError(name)


def dial_address(bind: str, connect: str | None = None) -> str:
    """The address peers connect to: the explicit one, else the bind with wildcards made local."""
    if connect:
        return connect
    return (bind.replace("://*:", "://127.0.0.1:").replace("://0.0.0.0:", "://127.0.0.1:")
            .replace("://[::]:", "://[::1]:"))


STRATEGIES = ("ip", "smg", "eps", "none")
ENGINE_KINDS = ("auto", "monolithic", "robion", "disagg", "static", "disjoint", "procdisagg", "interdisagg")  # ENGINES in engine.py
PROCDISAGG_WORKERS = ("process", "thread")
POLICIES = ("esf", "rr", "lqf")
SM_POLICIES = ("table", "none", "static")
NETWORKS = ("wifi7", "fast_cloud", "slow_cloud", "5g", "none")


# ----------------------------------------------------------------------------- generic loader

def _type_name(tp: Any) -> str:
    return {str: "a string", int: "an integer", float: "a number", bool: "true or false"}.get(tp, getattr(tp, "__name__", str(tp)))


def _convert(value: Any, tp: Any, path: str) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _convert(value, args[0], path)
    if origin is list:
        (item_tp,) = typing.get_args(tp)
        if not isinstance(value, list):
            raise ConfigError(f"{path}: expected a list")
        return [_convert(v, item_tp, f"{path}[{i}]") for i, v in enumerate(value)]
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, path)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{path}: expected a number")
        try:
            return float(value)
        except OverflowError:  # an int past a float's range: as infinite as YAML's .inf, refused by the check
            return math.inf if value > 0 else -math.inf
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{path}: expected an integer")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path}: expected true or false")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path}: expected a string")
        if "\0" in value:  # no path, name or address holds one; a file name with one crashed its service (ValueError)
            raise ConfigError(f"{path}: a NUL character is not allowed")
        return value
    raise ConfigError(f"{path}: unsupported type {tp}")


def _build(cls: type, data: Any, path: str) -> Any:
    if not isinstance(data, dict):
        raise ConfigError(f"{path or 'config'}: expected a mapping")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    prefix = f"{path}." if path else ""
    for key in data:
        if key not in fields:
            raise ConfigError(f"{prefix}{key}: unknown key (expected one of: {', '.join(fields)})")
    kwargs = {}
    for name, f in fields.items():
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{prefix}{name}: missing")
            continue
        value = _convert(data[name], hints[name], f"{prefix}{name}")
        check = f.metadata.get("check")
        if check and value is not None and not check[0](value):
            raise ConfigError(f"{prefix}{name}: {check[1]}")
        if isinstance(value, int) and not isinstance(value, bool) and not INT_MIN <= value <= INT_MAX:
            raise ConfigError(f"{prefix}{name}: {check[1] if check else 'expected an integer'} below 2**63")
        kwargs[name] = value
    return cls(**kwargs)


# ----------------------------------------------------------------------------- cluster rules

def _one_of(value: str, choices: tuple[str, ...], path: str) -> None:
    if value not in choices:
        raise ConfigError(f"{path}: expected one of {', '.join(choices)}, got {value!r}")


def _unique_names(names: list[str], path: str) -> set[str]:
    seen: set[str] = set()
    for i, name in enumerate(names):
        if not name or name in seen:
            raise ConfigError(f"{path}[{i}].name: {'empty' if not name else f'duplicate name {name!r}'}")
        seen.add(name)
    return seen


def bound_addresses(cfg: ClusterConfig) -> list[tuple[str, str]]:
    """(config key, address) of every address the cluster's services bind: the router's two and the control plane's."""
    return [("router.bind", cfg.router.bind), ("router.backend", cfg.router.backend), ("control.bind", cfg.control.bind)]


def executor_name_problem(name: str) -> str | None:
    """What keeps ``name`` from naming an executor, if anything. It is the executor's ZeroMQ socket identity: at most
    255 bytes, and one starting with a zero byte is reserved by ZeroMQ (either failed only when the executor bound
    its sockets, as a traceback). A leading "-" would read as an option on the executor's command line."""
    if len(name.encode()) > MAX_EXECUTOR_NAME_BYTES or name.startswith(("\0", "-")):
        return f"expected at most {MAX_EXECUTOR_NAME_BYTES} bytes (UTF-8), not starting with a zero byte or '-'"
    return None


def import_modules(names: list[str], folder: Path | None = None) -> None:
    """Import the ``imports`` of a config (their @register decorators add architectures). ``folder``, the
    config file's, is searched after sys.path, so a module beside the config never shadows an installed one."""
    if folder is not None and names and str(folder) not in sys.path:
        sys.path.append(str(folder))
    for i, name in enumerate(names):
        if not name or not all(part.isidentifier() for part in name.split(".")):
            raise ConfigError(f"imports[{i}]: expected a Python module name such as my_vla or pkg.models, got {name!r}")
        try:
            importlib.import_module(name)
        except (Exception, SystemExit) as exc:
            # Its own import errors included: the operator's module, named with the cause. SystemExit too (a module
            # that parses sys.argv or calls sys.exit at import): it ended the control plane on a `ctl apply`.
            raise ConfigError(f"imports[{i}]: cannot import {name!r} ({type(exc).__name__}: {exc})") from None


def _validate(cfg: ClusterConfig, folder: Path | None = None) -> None:
    from shared.models.base import VLAModel
    from shared.models.registry import architectures

    import_modules(cfg.imports, folder)
    try:
        archs = architectures()
    except ImportError as exc:  # a bad $ROBION_IMPORTS entry: one line and exit 2, like a bad `imports`
        raise ConfigError(str(exc)) from None
    if not cfg.models:
        raise ConfigError("models: at least one model is needed")
    seen = _unique_names([m.name for m in cfg.models], "models")
    for i, m in enumerate(cfg.models):
        if m.arch not in archs:
            raise ConfigError(f"models[{i}].arch: unknown architecture {m.arch!r} (known: {', '.join(sorted(archs))})")
        missing = [s for s in ("vlm_stage", "action_stage") if getattr(archs[m.arch], s) is getattr(VLAModel, s)]
        if missing:  # else the executor's start failed on NotImplementedError
            raise ConfigError(f"models[{i}].arch: {m.arch} ({archs[m.arch].__name__}) does not implement "
                              f"{' and '.join(missing)}, so it cannot be served (docs/models.md)")
        sizes = getattr(archs[m.arch], "CONFIGS", {})
        if m.size not in sizes:
            raise ConfigError(f"models[{i}].size: {m.arch} has no size {m.size!r} (sizes: {', '.join(sorted(sizes))})")
    if not cfg.executors:
        raise ConfigError("executors: at least one executor is needed")
    if len(cfg.executors) > MAX_EXECUTORS:  # the planner refuses more; say so at load, not at every solve
        raise ConfigError(f"executors: at most {MAX_EXECUTORS} executors in one cluster, got {len(cfg.executors)}")
    _unique_names([e.name for e in cfg.executors], "executors")
    for j, e in enumerate(cfg.executors):
        why = executor_name_problem(e.name)
        if why:
            raise ConfigError(f"executors[{j}].name: {why}")
        if not e.models:
            raise ConfigError(f"executors[{j}].models: an executor needs at least one model")
        for k, name in enumerate(e.models):
            if name not in seen:
                raise ConfigError(f"executors[{j}].models[{k}]: no model named {name!r}")
            if name in e.models[:k]:  # the planner would report it under a path this file does not have
                raise ConfigError(f"executors[{j}].models[{k}]: {name!r} is listed twice")
        if not valid_device(e.device):
            raise ConfigError(f"executors[{j}].device: expected 'cpu' or 'cuda:N', got {e.device!r}")
    hosted = {name for e in cfg.executors for name in e.models}
    for i, m in enumerate(cfg.models):
        if m.name not in hosted:
            raise ConfigError(f"models[{i}]: model {m.name!r} is placed on no executor")
    binds = {}
    for key, address in bound_addresses(cfg):
        if address in binds:  # else the second service to start failed to bind, as if another cluster held it
            raise ConfigError(f"{key}: {address} is {binds[address]} too; each service binds an address of its own")
        binds[address] = key
    _validate_engine(cfg.engine)
    _one_of(cfg.control.strategy, STRATEGIES, "control.strategy")
    _one_of(cfg.control.limits.network, NETWORKS, "control.limits.network")
    _one_of(cfg.fleet.network, NETWORKS, "fleet.network")
    for k, name in enumerate(cfg.fleet.models or []):
        if name not in seen:
            raise ConfigError(f"fleet.models[{k}]: no model named {name!r}")


def engine_config(data: dict) -> EngineConfig:
    """An EngineConfig from a mapping (a config's `engine:`, a benchmark's overrides) with every check a
    config file gets, so a benchmark refuses what a cluster would instead of measuring it."""
    e = _build(EngineConfig, data, "engine")
    _validate_engine(e)
    return e


def _validate_engine(e: EngineConfig) -> None:
    """Rules of the engine's knobs beyond each field's own (the generic checks ran while loading)."""
    _one_of(e.kind, ENGINE_KINDS, "engine.kind")
    _one_of(e.policy, POLICIES, "engine.policy")
    _one_of(e.sm_policy, SM_POLICIES, "engine.sm_policy")
    if e.sm_policy == "static" and (e.static_sms <= 0 or e.static_sms % 8):
        raise ConfigError("engine.static_sms: sm_policy static needs a positive multiple of 8")
    if e.kind == "static" and e.static_sms % 8:
        raise ConfigError("engine.static_sms: engine static needs a multiple of 8 (0: half the SMs)")
    if e.disjoint_sms % 8:
        raise ConfigError("engine.disjoint_sms: expected a multiple of 8 (0: profiled at start-up)")
    if e.running_batch and e.running_batch < e.max_batch:
        raise ConfigError(f"engine.running_batch: must be at least max_batch ({e.max_batch}), or 0 for 4 x max_batch")
    _one_of(e.procdisagg_workers, PROCDISAGG_WORKERS, "engine.procdisagg_workers")
    for key in ("vlm_devices", "action_devices"):
        try:
            parse_devices(getattr(e, key), required=e.kind == "interdisagg")
        except ValueError as exc:
            raise ConfigError(f"engine.{key}: {exc}") from None


def parse_devices(text: str, required: bool = False) -> list[str]:
    """A device list of engine interdisagg -> torch device strings, one per stage worker.

    Entries are separated by ",", "+" or spaces; each is "cpu", "cuda:N" or a bare index N
    (= "cuda:N"). ``"0+1"`` -> ``["cuda:0", "cuda:1"]``. A device may repeat (two workers on
    it). Raises ValueError with the reason.
    """
    out = []
    for item in filter(None, (s.strip() for s in text.replace("+", ",").replace(" ", ",").split(","))):
        if valid_device(f"cuda:{item}"):
            out.append(f"cuda:{item}")
        elif valid_device(item):
            out.append(item)
        else:
            raise ValueError(f"{item!r} is not a device (expected 'cpu', 'cuda:N' or an index N)")
    if required and not out:
        raise ValueError("engine interdisagg needs at least one device, e.g. 'cuda:0' or '0+1' ('cpu' on a CPU)")
    return out


def _expand_placement(data: Any) -> Any:
    """Turn the placement shorthands into an explicit executors list.

    ``gpus: N`` makes executors gpu0..gpuN-1 on cuda:0..N-1 (or with ``device: cpu``-only hosts, give
    ``executors`` instead). ``placement: mix`` puts every model on every executor (replication and
    co-location); ``placement: {groups: {pi0: 2, xr0: 2}}`` or ``{groups: [{arch: pi0, gpus: [0, 1]}, ...]}``
    splits the executors into disjoint groups, each serving every model of one architecture.
    """
    if not isinstance(data, dict) or ("gpus" not in data and "placement" not in data):
        return data
    data = dict(data)
    gpus = data.pop("gpus", None)
    placement = data.pop("placement", None)
    models = data.get("models")
    if not isinstance(models, list) or not all(isinstance(m, dict) for m in models):
        raise ConfigError("models: expected a list of mappings")
    if gpus is not None:
        if "executors" in data:
            raise ConfigError("gpus: give either gpus or executors, not both")
        if isinstance(gpus, bool) or not isinstance(gpus, int) or gpus < 1:
            raise ConfigError("gpus: expected a positive integer")
        if gpus > MAX_EXECUTORS:  # before a list of that many executors is built
            raise ConfigError(f"gpus: at most {MAX_EXECUTORS} executors in one cluster, got {gpus}")
        if placement is None:  # the GPUs it makes list no models: say so here, not at executors[0].models
            raise ConfigError("placement: gpus: N needs placement: mix or placement: {groups: ...} to say which "
                              "models each GPU serves")
        data["executors"] = [{"name": f"gpu{j}", "device": f"cuda:{j}", "models": []} for j in range(gpus)]
    executors = data.get("executors")
    if not isinstance(executors, list) or not all(isinstance(e, dict) for e in executors):
        raise ConfigError("executors: expected a list of mappings (or gpus: N)")
    executors = [dict(e) for e in executors]
    data["executors"] = executors
    # The shorthands copy model names into the executors' lists before the models themselves are
    # checked, so a missing or non-string name must be reported here, with its path, not as a KeyError.
    for i, m in enumerate(models):
        if "name" not in m:
            raise ConfigError(f"models[{i}].name: missing")
        if not isinstance(m["name"], str):
            raise ConfigError(f"models[{i}].name: expected a string")
    names = [m["name"] for m in models]
    if placement is None:
        return data
    if any(e.get("models") for e in executors):
        raise ConfigError("placement: executors already list their models; use one or the other")
    if placement == "mix":
        for e in executors:
            e["models"] = list(names)
        return data
    if not isinstance(placement, dict) or set(placement) != {"groups"}:
        raise ConfigError("placement: expected 'mix' or {groups: ...}")
    groups = placement["groups"]
    if isinstance(groups, dict):  # {arch: number of GPUs}, assigned in order
        spec, start = [], 0
        for arch, count in groups.items():
            if not isinstance(arch, str):
                raise ConfigError(f"placement.groups.{arch}: expected an architecture name")
            if isinstance(count, bool) or not isinstance(count, int) or count < 1:
                raise ConfigError(f"placement.groups.{arch}: expected a positive number of GPUs")
            spec.append({"arch": arch, "gpus": list(range(start, start + count))})
            start += count
        groups = spec
    if not isinstance(groups, list):
        raise ConfigError("placement.groups: expected a mapping {arch: gpus} or a list of {arch, gpus}")
    # Before the groups look models up by arch: a list there was reported as the group's arch serving nothing, and
    # below, in a set, it would raise TypeError.
    for i, m in enumerate(models):
        if not isinstance(m.get("arch", ""), str):
            raise ConfigError(f"models[{i}].arch: expected a string")
    used: dict[int, str] = {}
    for g, group in enumerate(groups):
        path = f"placement.groups[{g}]"
        if not isinstance(group, dict) or set(group) != {"arch", "gpus"}:
            raise ConfigError(f"{path}: expected {{arch, gpus}}")
        arch, idx = group["arch"], group["gpus"]
        if not isinstance(arch, str):  # it becomes a set member and a dict key below
            raise ConfigError(f"{path}.arch: expected an architecture name")
        if not isinstance(idx, list) or not idx:
            raise ConfigError(f"{path}.gpus: the group is empty")
        members = [m["name"] for m in models if m.get("arch") == arch]
        if not members:
            raise ConfigError(f"{path}.arch: no model of architecture {arch!r} to serve: the group is empty")
        for j in idx:
            if isinstance(j, bool) or not isinstance(j, int) or not 0 <= j < len(executors):
                raise ConfigError(f"{path}.gpus: {j!r} is not a GPU index below {len(executors)}")
            if j in used:
                raise ConfigError(f"{path}.gpus: GPU {j} is already in the {used[j]} group; groups are disjoint")
            used[j] = arch
            executors[j]["models"] = list(members)
    unserved = [m["name"] for m in models if m.get("arch") not in {gr["arch"] for gr in groups}]
    if unserved:
        raise ConfigError(f"placement.groups: no group serves {unserved}")
    idle = [executors[j].get("name") for j in range(len(executors)) if j not in used]
    if idle:
        raise ConfigError(f"placement.groups: executors {idle} are in no group")
    return data


def config_from_dict(data: Any, folder: Path | None = None) -> ClusterConfig:
    """A checked config from parsed YAML; ``folder`` (the file's) is searched for its ``imports``."""
    cfg = _build(ClusterConfig, _expand_placement(data), "")
    _validate(cfg, folder)
    if any(e.memory_gb is not None for e in cfg.executors):
        from shared.placement import check_fit

        check_fit(cfg)
    return cfg


def load_config(path: str | Path) -> ClusterConfig:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError as exc:  # a Latin-1 comment, or a binary file named by mistake
        raise ConfigError(f"{path}: not a UTF-8 text file (byte {exc.start})") from None
    return config_from_text(text, str(path), path.resolve().parent)


def parse_yaml(text: str) -> Any:
    """``load_yaml`` with every way it can fail as a ConfigError saying where: a repeated key, text that is
    not YAML, nesting too deep. Cluster configs and planning files are both read through this."""
    try:
        return load_yaml(text)
    except DuplicateKeyError as exc:
        raise ConfigError(str(exc)) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(f"not valid YAML{where}") from None
    except RecursionError:  # PyYAML composes nested collections recursively
        raise ConfigError("not valid YAML (nested too deeply)") from None


def config_from_text(text: str, source: str = "config", folder: Path | None = None) -> ClusterConfig:
    """A checked config from YAML text (a file's, or one sent with `robion ctl apply`); ``source`` names it."""
    try:
        data = parse_yaml(text)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    return config_from_dict(data, folder)
