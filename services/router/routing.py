"""Picking the executor for a request from the control plane's routing table."""

from __future__ import annotations

from shared.control import RoutingTable


class Routing:
    """Round-robin over the executors hosting a model, from the latest table."""

    def __init__(self) -> None:
        self.table = RoutingTable()
        self._next: dict[str, int] = {}

    def update(self, table: RoutingTable) -> set[str]:
        """Swap in a newer table in one assignment; returns executors that left it."""
        before = {e for ex in self.table.routes.values() for e in ex}
        self.table = table
        after = {e for ex in table.routes.values() for e in ex}
        return before - after

    def candidates(self, model: str) -> list[str]:
        """Executors to try for ``model``, the round-robin choice first; empty when none hosts it."""
        execs = self.table.routes.get(model, [])
        if not execs:
            return []
        i = self._next.get(model, 0) % len(execs)
        self._next[model] = i + 1
        return execs[i:] + execs[:i]

    def knows(self, model: str) -> bool:
        return model in self.table.models
