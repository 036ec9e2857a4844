"""Picking the executor for a request from the control plane's routing table.

With a traffic assignment in the table, each robot is pinned to one executor for its model
so that the robots per (model, executor) follow the solver's quotas; a robot beyond the
declared population goes to the least-loaded executor hosting its model. Without one,
requests are spread round-robin.
"""

from __future__ import annotations

import time
from collections import Counter

from shared.control import RoutingTable

MAX_PINNED_ROBOTS = 100_000
# A robot silent this long gives its place in an executor's quota back (release_idle). Robots call
# several times a second; one that left for good used to hold its place until the next solve, and the
# robots that came in meanwhile were sent beyond the quotas, to the least-loaded executor.
PIN_IDLE_S = 60.0


class Routing:
    def __init__(self) -> None:
        self.table = RoutingTable()
        self._next: dict[str, int] = {}
        self.pins: dict[tuple[bytes, str], str] = {}  # (robot, model) -> executor
        self.assigned: Counter[tuple[str, str]] = Counter()  # (model, executor) -> pinned robots
        self.pin_used: dict[tuple[bytes, str], float] = {}  # (robot, model) -> when it last asked

    def update(self, table: RoutingTable) -> set[str]:
        """Swap in a newer table in one assignment; returns executors that are gone (not merely draining).

        Pins that still fit the new routes and quotas are kept, so a re-solve moves only the
        robots it has to.
        """
        before = set(self.table.executors)
        self.table = table
        after = set(table.executors)
        pins: dict[tuple[bytes, str], str] = {}
        counts: Counter[tuple[str, str]] = Counter()
        for (robot, model), ex in self.pins.items():
            quota = table.quotas.get(model)
            if quota and ex in table.routes.get(model, []) and counts[(model, ex)] < quota.get(ex, 0):
                pins[(robot, model)] = ex
                counts[(model, ex)] += 1
        self.pins, self.assigned = pins, counts
        self.pin_used = {k: t for k, t in self.pin_used.items() if k in pins}
        return before - after

    def candidates(self, model: str, robot: bytes = b"", now: float | None = None) -> list[str]:
        """Executors to try for ``model``, the chosen one first; empty when none hosts it."""
        execs = self.table.routes.get(model, [])
        if not execs:
            return []
        if not self.table.quotas.get(model):
            i = self._next.get(model, 0) % len(execs)
            self._next[model] = i + 1
            return execs[i:] + execs[:i]
        chosen = self.pins.get((robot, model))
        if chosen not in execs:
            chosen = self._pin(model, robot, execs)
        self.pin_used[(robot, model)] = time.monotonic() if now is None else now
        return [chosen] + [e for e in execs if e != chosen]

    def _pin(self, model: str, robot: bytes, execs: list[str]) -> str:
        quota = self.table.quotas[model]
        room = {e: quota.get(e, 0) - self.assigned[(model, e)] for e in execs}
        best = max(execs, key=lambda e: room[e])
        if room[best] <= 0:  # beyond the declared population: least-loaded GPU by its share of capacity
            best = min(execs, key=self._load)
        if len(self.pins) >= MAX_PINNED_ROBOTS:
            self.pins.clear()
            self.assigned.clear()
            self.pin_used.clear()
        self.pins[(robot, model)] = best
        self.assigned[(model, best)] += 1
        return best

    def release_idle(self, now: float, idle_s: float = PIN_IDLE_S) -> int:
        """Unpin the robots that have not asked for ``idle_s``; returns how many. One that comes back is
        pinned again like a new robot."""
        idle = [k for k, t in self.pin_used.items() if now - t > idle_s]
        for key in idle:
            del self.pin_used[key]
            ex = self.pins.pop(key, None)
            if ex is not None:
                self.assigned[(key[1], ex)] -= 1
        return len(idle)

    def _load(self, executor: str) -> float:
        limits = self.table.limits
        return sum(n / limits.get(m, 1) for (m, e), n in self.assigned.items() if e == executor)

    def knows(self, model: str) -> bool:
        """A model the cluster serves, whether or not an executor hosts it right now.

        The control plane lists every configured model in ``models`` (or, before any executor
        described it, as an empty route); one without executors is unavailable, not unknown.
        """
        return model in self.table.models or model in self.table.routes
