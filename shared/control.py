"""Control messages between services (single msgpack frames, never seen by robots).

executor -> control plane: register {executor, device, instance, models: {name: ModelInfo}, limits: {name: int},
                                     load: {id, ok, error?} or None (the outcome of its last `load`),
                                     settings: {name: digest of the model's settings}}
                                                     -> registered {version}
                           heartbeat {executor, depths}  (answered only by reregister, when unknown)
                           deregister {executor}         (not answered)
                           drain {executor}              -> ok {version}  (itself, as it shuts down: sent from
                                                            its own socket, this drain ends with the process)
router   -> control plane: table_get {version, role, executors?}
                                                     -> table {table: {version, models, routes, ...} or None}
                           (None: nothing newer, or a just-started plane holding its first table while the
                           executors that outlived its restart register again; after each (re)connect to
                           the control plane a router reports version -1 and names its table's executors)
anyone   -> control plane: status                    -> status {executors, table, router, expected, limits,
                                                                control, settling, ready, rollout, apply,
                                                                drift}
control plane -> executor: load {models: [model config], load_id}  (a placement change's reload; not answered:
                           the executor registers again once it is over, its `load` naming load_id)
operator -> control plane: apply {config}            -> applied {steps, version, unhosted, awaiting, host_wait_s,
                                                                 rollout}
                           drain / resume {executor} -> ok {version, unrouted}  (unrouted: the models a drain
                           left without a route, of which it was the only host)
executor -> router (backend, empty robot frame): executor_hello {executor, instance, connection?}  (not
                           answered; at each connect and each heartbeat while connected. The instance is the
                           process's token, as in register: a new one under a known name is a restarted
                           executor, and the router answers its requests in flight UNAVAILABLE. connection
                           counts the process's connects: a new number of a known instance is a reconnect,
                           and its requests from before still unanswered 3 s later are answered UNAVAILABLE)

A message the control plane cannot act on is answered error {code, message}: `message` is for
people and names the bad field; `code` is stable (ControlError). A well-formed heartbeat or
deregister is still not answered. A robot limit in `limits` that is not a positive integer is
ignored with a warning (the rest of the registration, and its valid limits, are kept).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Any

from shared.protocol import ModelInfo, pack_header, unpack_map

# Control messages pass only between Robion's own processes (control plane, router, executors, the operator
# CLI), never from robots, and they grow with the cluster: the routing table (and `status`, which carries it)
# holds every model's description, routes and one quota per (model, executor), so 300 fine-tuned variants on
# 64 GPUs make about 75 KB and every model on every GPU far more; an `apply` carries the whole config file.
# A robot header's limits (64 KiB, 1024 map entries) would make the router refuse such a table and keep
# routing by a stale one for good, so control messages get their own. They still bound what a peer on the
# control socket can make msgpack allocate.
MAX_CONTROL_BYTES = 16 * 1024 * 1024
MAX_CONTROL_LEN = 1 << 20  # entries in any one map or array of a control message


def pack(kind: str, **fields: Any) -> bytes:
    return pack_header({"kind": kind, **fields})


def unpack(frame: bytes | memoryview) -> dict[str, Any]:
    """Decode a control message; ProtocolError (TOO_LARGE, BAD_REQUEST) when it cannot be read."""
    return unpack_map(frame, max_bytes=MAX_CONTROL_BYTES, max_map_len=MAX_CONTROL_LEN, max_array_len=MAX_CONTROL_LEN,
                      what="control message")


class ControlError(str, Enum):
    """The `code` of the control plane's error replies: stable, for programs to act on."""

    BAD_REQUEST = "BAD_REQUEST"  # not msgpack, not a map, unknown kind, a missing or mistyped field
    TOO_LARGE = "TOO_LARGE"  # a message beyond MAX_CONTROL_BYTES
    BAD_CONFIG = "BAD_CONFIG"  # apply: the new config is not valid YAML or fails validation
    RESTART_REQUIRED = "RESTART_REQUIRED"  # apply: it changes settings read only at start-up
    BUSY = "BUSY"  # apply: a placement change is still in progress
    UNKNOWN_EXECUTOR = "UNKNOWN_EXECUTOR"  # drain / resume: no executor of that name is registered
    INTERNAL = "INTERNAL"  # an unforeseen failure on the control plane (its log has the traceback)


def error(code: ControlError | str, message: str) -> bytes:
    return pack("error", code=ControlError(code).value, message=message)


class TableError(ValueError):
    """A routing table on the wire that cannot be read (RoutingTable.from_wire)."""


@dataclass
class RoutingTable:
    """Which executors serve which model: the control plane's decision, applied by the router."""

    version: int = 0
    models: dict[str, ModelInfo] = field(default_factory=dict)
    routes: dict[str, list[str]] = field(default_factory=dict)  # model -> executors hosting it
    # The traffic controller's solution: robots of a model each executor takes (empty: round-robin per request).
    quotas: dict[str, dict[str, int]] = field(default_factory=dict)
    limits: dict[str, int] = field(default_factory=dict)  # model -> robots one GPU sustains (C_i)
    executors: list[str] = field(default_factory=list)  # every registered executor, draining ones included

    def to_wire(self) -> dict[str, Any]:
        return {"version": self.version, "models": {n: i.to_wire() for n, i in self.models.items()},
                "routes": {m: list(e) for m, e in self.routes.items()},
                "quotas": {m: dict(q) for m, q in self.quotas.items()}, "limits": dict(self.limits),
                "executors": list(self.executors)}

    @classmethod
    def from_wire(cls, d: dict[str, Any]) -> "RoutingTable":
        """Raises TableError, naming the field, for a table that cannot be read (a wrong shape or value anywhere).

        Strict on shape: nothing is converted into what it should have been. A str where a list of
        executors belongs is not taken for its characters, nor "7" or 2.9 for version 7 or 2.
        """
        if not isinstance(d, dict):
            raise TableError(f"malformed routing table: expected a map, got {type(d).__name__}")
        if "version" not in d:
            raise TableError("malformed routing table: version: missing")
        if "models" not in d or "routes" not in d:
            raise TableError(f"malformed routing table: {'models' if 'models' not in d else 'routes'}: missing")
        version = _int(d["version"], "version")
        models = {}
        for name, info in _str_map(d["models"], "models").items():
            try:
                models[name] = ModelInfo.from_wire(info)
            except ValueError as exc:
                raise TableError(f"malformed routing table: models[{name!r}]: {exc}") from None
        routes = {m: _str_list(e, f"routes[{m!r}]") for m, e in _str_map(d["routes"], "routes").items()}
        quotas = {m: {e: _int(n, f"quotas[{m!r}][{e!r}]") for e, n in _str_map(q, f"quotas[{m!r}]").items()}
                  for m, q in _str_map(d.get("quotas", {}), "quotas").items()}
        limits = {m: _int(c, f"limits[{m!r}]") for m, c in _str_map(d.get("limits", {}), "limits").items()}
        executors = _str_list(d.get("executors", []), "executors")
        return cls(version=version, models=models, routes=routes, quotas=quotas, limits=limits, executors=executors)


def _int(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TableError(f"malformed routing table: {name}: expected an int, got {type(value).__name__} {value!r:.80}")
    return value


def _str_map(value: Any, name: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise TableError(f"malformed routing table: {name}: expected a map, got {type(value).__name__}")
    for key in value:
        if not isinstance(key, str):
            raise TableError(f"malformed routing table: {name}: expected str keys, got {type(key).__name__} "
                             f"{key!r:.80}")
    return value


def _str_list(value: Any, name: str) -> list[str]:
    if not isinstance(value, (list, tuple)) or not all(isinstance(x, str) for x in value):
        raise TableError(f"malformed routing table: {name}: expected a list of executor names (str), got "
                         f"{value!r:.80}")
    return list(value)
