"""Control messages between services (single msgpack frames, never seen by robots).

executor -> control plane: register {executor, device, instance, models: {name: ModelInfo}, limits: {name: int}}
                                                     -> registered {version}
                           heartbeat {executor, depths}  (answered only by reregister, when unknown)
                           deregister {executor}         (not answered)
router   -> control plane: table_get {version, role}  -> table {table: {version, models, routes, ...} or None}
anyone   -> control plane: status                    -> status {executors, table, router, expected, limits,
                                                                ready, rollout}
operator -> control plane: apply {config}            -> applied {steps, version}
                           drain / resume {executor} -> ok {version}
executor -> router (backend, empty robot frame): executor_hello {executor, instance}  (not answered; the
                           instance is the process's token, as in register: a new one under a known name
                           is a restarted executor, and the router answers its requests in flight UNAVAILABLE)

A message the control plane cannot act on is answered error {code, message}: `message` is for
people and names the bad field; `code` is stable (ControlError). A well-formed heartbeat or
deregister is still not answered. A robot limit in `limits` that is not a positive integer is
ignored with a warning (the rest of the registration, and its valid limits, are kept).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Any

from shared.protocol import ModelInfo, pack_header, unpack_header


def pack(kind: str, **fields: Any) -> bytes:
    return pack_header({"kind": kind, **fields})


def unpack(frame: bytes | memoryview) -> dict[str, Any]:
    return unpack_header(frame)


class ControlError(str, Enum):
    """The `code` of the control plane's error replies: stable, for programs to act on."""

    BAD_REQUEST = "BAD_REQUEST"  # not msgpack, not a map, unknown kind, a missing or mistyped field
    TOO_LARGE = "TOO_LARGE"  # a message beyond the header size limit
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
        """Raises TableError for a table that cannot be read (a wrong shape or value anywhere in it)."""
        try:
            return cls(version=int(d["version"]), models={n: ModelInfo.from_wire(i) for n, i in d["models"].items()},
                       routes={m: [str(x) for x in e] for m, e in d["routes"].items()},
                       quotas={m: {str(e): int(n) for e, n in q.items()} for m, q in d.get("quotas", {}).items()},
                       limits={m: int(c) for m, c in d.get("limits", {}).items()},
                       executors=[str(e) for e in d.get("executors", [])])
        # What the conversions above raise on a wrong shape or value: a missing key, a non-map
        # (indexing a str or list, .items() on a list), int("x"), int(inf). Turned into one error
        # type so the router can catch "not a table" and nothing that fails while applying one.
        except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
            raise TableError(f"malformed routing table ({type(exc).__name__}: {exc})") from None
