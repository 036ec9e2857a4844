"""The control plane's view of the cluster: registered executors and the routing table."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

from services.controlplane.traffic import Quotas, assign
from shared.config import ClusterConfig, ModelConfig, settings_digest
from shared.control import RoutingTable
from shared.protocol import ModelInfo

log = logging.getLogger("robion.control")

# How long a control plane that has just started holds back its routing table, at most, in heartbeat
# intervals. After a restart of the control plane, the executors that kept running learn of it from
# their next heartbeat (answered "reregister") and register again within about one interval. A table
# published before they have would drop them from the router's routes and fail the requests they hold;
# the router keeps the old plane's table meanwhile (ClusterState.settled says when the hold ends early).
SETTLE_HEARTBEATS = 3
# After the first router's poll, how long the hold waits at least for other routers to name their executors.
ROUTERS_GRACE_S = 0.5
MAX_AWAITED = 4096  # executor names routers may add to the hold (each at most MAX_NAME_CHARS)
MAX_NAME_CHARS = 255


def limit_basis(model: ModelConfig) -> tuple:
    """The settings of a model a measured robot limit depends on (the engine's are fixed while the plane runs)."""
    return (model.arch, model.size, model.hz, model.slo_ms)


def valid_limit(value: object) -> bool:
    """A robot limit C_i is a positive integer, as in the config; msgpack true is not an integer here."""
    return isinstance(value, int) and not isinstance(value, bool) and value > 0


@dataclass
class ExecutorState:
    name: str
    device: str
    models: dict[str, ModelInfo]
    last_seen: float
    depths: dict[str, int] = field(default_factory=dict)
    # registered and serving what it holds, but routed nothing new, for a placement change (rollout.py);
    # an operator's drain is ClusterState.drained, which outlives this entry
    draining: bool = False
    instance: str = ""  # the executor process's token: another one after a restart
    # A digest of each served model's settings (shared.config.settings_digest), as the executor registered them;
    # None from an executor that sent none. What an apply compares with, rather than the file before it.
    settings: dict[str, str] | None = None


class ClusterState:
    """Executors come and go by heartbeat; the routing table follows, versioned."""

    def __init__(self, cfg: ClusterConfig):
        self.cfg = cfg
        self.executors: dict[str, ExecutorState] = {}
        self.table = RoutingTable(version=0)
        self.router_seen = 0.0
        self.router_version = -1
        self.quotas = Quotas({}, {})
        self.measured_limits: dict[str, int] = {}  # robot limits reported by executors
        # The latest description of each model an executor registered; it outlives that
        # executor, so a configured model stays describable while no host serves it.
        self.described: dict[str, ModelInfo] = {}
        # Executors an operator drained (`robion ctl drain`), until `resume`. Kept by name, apart from the
        # registry entries: an executor that misses its heartbeats or restarts comes back as a new
        # entry, and a placement change ends its own drain; neither is the operator's resume.
        self.drained: set[str] = set()
        self.started = time.monotonic()
        self._settled = False
        self.router_heard: float | None = None  # when a router that noticed the restart first asked for a table
        # Executors a router still routes to by an earlier control plane's table (it names them while its
        # table outlives that plane): replicas scaled out beside the config are known only this way.
        self.awaited: set[str] = set()
        self.departed: set[str] = set()  # executors that deregistered during the hold: not waited for

    def settled(self, now: float | None = None) -> bool:
        """Whether the routing table may be published. It is once a router has asked for one (and other
        routers have had ROUTERS_GRACE_S to) and every executor configured or named by a router
        (``awaited``) has registered or left, once SETTLE_HEARTBEATS heartbeat intervals have passed since
        this control plane started, or once ``settle`` was called."""
        if not self._settled:
            now = now or time.monotonic()
            expected = ({e.name for e in self.cfg.executors} | self.awaited) - self.departed
            everyone = (self.router_heard is not None and now - self.router_heard >= ROUTERS_GRACE_S
                        and expected <= set(self.executors))
            self._settled = everyone or now - self.started >= SETTLE_HEARTBEATS * self.cfg.control.heartbeat_s
        return self._settled

    def hear_router(self, version: int, executors: object, now: float | None = None) -> None:
        """A router's table poll during the hold: one reporting no table of this plane's (-1, or 0 without
        a table) has noticed the restart, and names the executors it still routes to (a list of names)."""
        if self._settled or version > 0:  # > 0: it has not noticed yet, and names nobody
            return
        if self.router_heard is None:
            self.router_heard = now or time.monotonic()
        if isinstance(executors, list):
            for name in executors[:MAX_AWAITED]:
                if len(self.awaited) >= MAX_AWAITED:
                    break
                if isinstance(name, str) and 0 < len(name) <= MAX_NAME_CHARS:
                    self.awaited.add(name)

    def settle(self) -> None:
        """End the hold now: a drain, resume or new config must reach the router at once (an executor that
        shuts down drains itself, then waits only a few seconds for the router to stop routing to it)."""
        self._settled = True

    @property
    def timeout_s(self) -> float:
        return self.cfg.control.heartbeat_s * self.cfg.control.missed_heartbeats

    def register(self, name: str, device: str, models: dict[str, ModelInfo], now: float | None = None,
                 limits: dict[str, int] | None = None, instance: str = "",
                 settings: dict[str, str] | None = None) -> None:
        # One bad measured limit (0, negative, a fraction, inf, NaN) would make the traffic plan
        # invalid for every model, so it is ignored; the executor's valid limits still count.
        limits = limits or {}
        bad = {m: c for m, c in limits.items() if not valid_limit(c)}
        if bad:
            log.warning("executor %s reported robot limits that are not positive integers, ignored: %s", name, bad)
        # A limit holds for the settings it was measured at. An executor that still runs a model's settings from
        # before an apply (restarted from its file, or back before its reload) reports the old settings' limit:
        # taken for the new ones, it would plan robots at another rate or deadline until a restart of the plane.
        stale = sorted(m for m, c in limits.items() if valid_limit(c) and not self._current(m, settings))
        if stale:
            log.warning("executor %s reported robot limits for settings other than the desired ones, ignored: %s",
                        name, stale)
        measured_before = dict(self.measured_limits)
        self.measured_limits.update({m: c for m, c in limits.items() if valid_limit(c) and m not in stale})
        self.described.update(models)
        old = self.executors.get(name)
        # A registry entry's drain (a placement change's, or the executor's own as it shuts down) belongs to
        # its process: another process under the name (one killed after its own drain leaves its entry until
        # its heartbeats time out) starts undrained; a rollout step drains a restarted executor again itself.
        draining = old is not None and old.draining and old.instance == instance
        self.executors[name] = ExecutorState(name, device, models, now or time.monotonic(),
                                             draining=draining, instance=instance, settings=settings)
        # A limit measured or changed since the last solve (a model's first measurement, one after a reload)
        # re-solves the quotas even when the routes stay the same.
        self._rebuild(force=self.measured_limits != measured_before)

    def _current(self, model: str, settings: dict[str, str] | None) -> bool:
        """Whether an executor's registered settings of ``model`` are the desired state's (None: it sent no digests,
        and is taken at its word)."""
        if settings is None:
            return True
        try:
            return settings.get(model) == settings_digest(self.cfg.model(model))
        except KeyError:
            return False

    def set_draining(self, name: str, draining: bool) -> bool:
        """A placement change's drain of a registered executor (lifted when its step ends)."""
        ex = self.executors.get(name)
        if ex is None:
            return False
        ex.draining = draining
        self._rebuild()
        return True

    def set_drained(self, name: str, drained: bool) -> bool:
        """An operator's drain or resume of a registered executor; False when none of that name is registered."""
        if name not in self.executors:
            return False
        if drained:
            self.drained.add(name)
        else:
            self.drained.discard(name)
        self._rebuild()
        return True

    def routed_nothing_new(self, name: str) -> bool:
        ex = self.executors.get(name)
        return name in self.drained or (ex is not None and ex.draining)

    def replace_config(self, cfg: ClusterConfig) -> None:
        """New desired state (placement, populations, limits): re-solve even if the routes stay.

        If the re-solve fails the running config stays the desired state, so a failed `apply`
        changes nothing (the table is only replaced once a solve succeeds).

        A measured limit holds for the settings it was measured at: one of a model whose architecture, size,
        rate or deadline changes (or that is gone) is dropped, and the executor that reloads it reports the
        one for its new settings, if it has it."""
        old, self.cfg = self.cfg, cfg
        measured = self.measured_limits
        before, after = {m.name: limit_basis(m) for m in old.models}, {m.name: limit_basis(m) for m in cfg.models}
        self.measured_limits = {m: c for m, c in measured.items() if m in before and before[m] == after.get(m)}
        try:
            self._rebuild(force=True)
        except BaseException:
            self.cfg, self.measured_limits = old, measured
            raise

    def heartbeat(self, name: str, depths: dict[str, int], now: float | None = None) -> bool:
        """False when the executor is unknown (it must register again, e.g. after a control-plane restart)."""
        ex = self.executors.get(name)
        if ex is None:
            return False
        ex.last_seen = now or time.monotonic()
        ex.depths = depths
        return True

    def deregister(self, name: str) -> None:
        if not self._settled:
            self.departed.add(name)
        if self.executors.pop(name, None) is not None:
            self._rebuild()

    def expire(self, now: float | None = None) -> list[str]:
        now = now or time.monotonic()
        gone = [n for n, e in self.executors.items() if now - e.last_seen > self.timeout_s]
        for n in gone:
            del self.executors[n]
        if gone:
            self._rebuild()
        return gone

    def _rebuild(self, force: bool = False) -> None:
        models: dict[str, ModelInfo] = {}
        routes: dict[str, list[str]] = {}
        for cfg_ex in self.cfg.executors:  # config order keeps round-robin order stable
            ex = self.executors.get(cfg_ex.name)
            if ex is None or self.routed_nothing_new(ex.name):
                continue
            for model, info in ex.models.items():
                models.setdefault(model, info)
                routes.setdefault(model, []).append(ex.name)
        for name, ex in self.executors.items():  # executors not in the config (scaled out by hand)
            if not self.routed_nothing_new(name) and all(e.name != name for e in self.cfg.executors):
                for model, info in ex.models.items():
                    models.setdefault(model, info)
                    routes.setdefault(model, []).append(name)
        # Every configured model stays in the table while no live, non-draining executor hosts it
        # (drained, crashed, not registered yet), with no route: the router then answers
        # UNAVAILABLE ("retry") rather than UNKNOWN_MODEL ("never retry"), and hello still lists
        # it. Its description is the last one an executor registered; a model no executor has
        # described yet cannot be listed in `models`, so it is published as an empty route.
        for mc in self.cfg.models:
            if mc.name in models:
                continue
            if mc.name in self.described:
                models[mc.name] = self.described[mc.name]
            else:
                routes[mc.name] = []
        # Draining executors stay listed: the router answers their requests in flight normally.
        executors = sorted(self.executors)
        if not force and (models, routes, executors) == (self.table.models, self.table.routes, self.table.executors):
            return
        # A new placement is a new solve: robots keep their executor only until then. GPUs are numbered in config
        # order, then replicas outside it, as `robion plan` numbers them: where plans tie, both pick the same one.
        configured = {e.name: None for e in self.cfg.executors}
        order = list(configured) + [n for n in self.executors if n not in configured]
        placement = {e: [m for m, execs in routes.items() if e in execs] for e in order}
        placement = {e: models_of for e, models_of in placement.items() if models_of}
        self.quotas = assign(self.cfg, placement, self.measured_limits)
        self.table = RoutingTable(version=self.table.version + 1, models=models, routes=routes,
                                  quotas=self.quotas.robots, limits=self.quotas.limits, executors=executors)

    def status(self, now: float | None = None) -> dict:
        now = now or time.monotonic()
        expected = [e.name for e in self.cfg.executors]
        return {
            "executors": {n: {"device": e.device, "models": sorted(e.models), "depths": e.depths,
                              "draining": self.routed_nothing_new(n), "instance": e.instance,
                              "last_seen_s": round(now - e.last_seen, 3)} for n, e in self.executors.items()},
            "expected": expected,
            "table": self.table.to_wire(),
            "limits": {m.name: m.limit if m.limit is not None else self.measured_limits.get(m.name) for m in self.cfg.models},
            "router": {"version": self.router_version,
                       "last_seen_s": round(now - self.router_seen, 3) if self.router_seen else None},
            # The live control settings (an apply changes them): how long an answer that re-solves may take.
            "control": {"strategy": self.cfg.control.strategy, "headroom": self.cfg.control.headroom,
                        "solve_time_limit_s": self.cfg.control.solve_time_limit_s},
            "settling": not self.settled(now),
            "ready": (all(n in self.executors for n in expected) and self.router_version == self.table.version
                      and self.router_seen > 0 and now - self.router_seen < 2.0),
        }
