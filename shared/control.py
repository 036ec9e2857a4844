"""Control messages between services (single msgpack frames, never seen by robots).

executor -> control plane: register {executor, device, models: {name: ModelInfo}}, heartbeat {executor, depths},
                           deregister {executor}
router   -> control plane: table_get {version}       -> table {version, models, routes}
anyone   -> control plane: status                    -> status {executors, table, router}
executor -> router (backend, empty robot frame): executor_hello {executor}
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from shared.protocol import ModelInfo, pack_header, unpack_header


def pack(kind: str, **fields: Any) -> bytes:
    return pack_header({"kind": kind, **fields})


def unpack(frame: bytes | memoryview) -> dict[str, Any]:
    return unpack_header(frame)


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
        return cls(version=int(d["version"]), models={n: ModelInfo.from_wire(i) for n, i in d["models"].items()},
                   routes={m: [str(x) for x in e] for m, e in d["routes"].items()},
                   quotas={m: {str(e): int(n) for e, n in q.items()} for m, q in d.get("quotas", {}).items()},
                   limits={m: int(c) for m, c in d.get("limits", {}).items()},
                   executors=[str(e) for e in d.get("executors", [])])
