"""Applying a new placement to a live cluster, one executor at a time.

For each executor whose models change: take it out of routing (draining; its requests in
flight are still answered), tell it to load the new model set, and put it back once it
registers with that set. Executors that gain models go first, and a step whose executor is the
only host of a model waits until another executor serves it, so a model moving between executors
keeps a host; where no order allows that (a swap), the step names the models left without one.
The routing table switches atomically at each step.
"""

from __future__ import annotations

import logging
import time
import uuid
from dataclasses import dataclass, field, fields, is_dataclass
from typing import Any, Callable, Iterable

from services.controlplane.state import ClusterState
from shared.config import ClusterConfig, ModelConfig, executor_settings, settings_digest

log = logging.getLogger("robion.control")

SendLoad = Callable[[str, list[ModelConfig], str], None]  # executor, its new models, the load's id


@dataclass
class Step:
    executor: str
    models: list[ModelConfig]
    started: float = 0.0
    drained_version: int = 0  # the table version without this executor's routes
    loading: bool = False
    instance: str = ""  # the executor process the load was sent to
    # Names the load sent. The executor's first registration after its reload carries {id, ok}: the outcome
    # is read from that, not guessed from the model names it registers. Names alone cannot tell new weights
    # (or a new rate or deadline) from the old ones kept after a failed reload, nor the registration of a
    # reload that failed from one the executor sends because it lost the control plane while reloading.
    load_id: str = ""
    # Models no other executor serves while this one reloads: their requests are answered UNAVAILABLE meanwhile
    # (a swap between two executors, a new setting of a model with a single host). plan_steps orders the
    # steps so that this is empty wherever an order allows it.
    unhosted: list[str] = field(default_factory=list)
    # Models the step drops that no executor registered and routed now is to serve once the rollout is done: their
    # new hosts are not running yet, or are drained. The step waits for another executor to serve them (one that
    # registers, or is resumed) and fails, keeping them, if none does: dropped, they had no host until an operator
    # started one, and the apply reported success.
    awaits: list[str] = field(default_factory=list)
    waiting_since: float = 0.0


# Settings `apply` changes live: the models (placement, populations, rates, limits, weights),
# which executor hosts which, and how robots are assigned. Everything else is read once by a
# process at start-up, so installing it as desired state would only make status disagree with
# what runs.
LIVE_CONTROL_FIELDS = frozenset({"strategy", "solve_time_limit_s", "headroom"})
LIVE_EXECUTOR_FIELDS = frozenset({"name", "models", "memory_gb"})  # memory_gb: checked at apply

def _differences(prefix: str, a: Any, b: Any, out: list[str]) -> None:
    if is_dataclass(a) and is_dataclass(b):
        for f in fields(a):
            _differences(f"{prefix}.{f.name}", getattr(a, f.name), getattr(b, f.name), out)
    elif a != b:
        out.append(f"{prefix}: {a!r} -> {b!r}")


def restart_only_changes(old: ClusterConfig, new: ClusterConfig) -> list[str]:
    """The settings that differ in ``new`` but take effect only when the processes restart."""
    out: list[str] = []
    if old.imports != new.imports:  # every process imports them as it starts; a reload could not build the models
        out.append(f"imports: {old.imports!r} -> {new.imports!r}")
    _differences("engine", old.engine, new.engine, out)
    _differences("router", old.router, new.router, out)
    for f in fields(old.control):
        if f.name not in LIVE_CONTROL_FIELDS:
            _differences(f"control.{f.name}", getattr(old.control, f.name), getattr(new.control, f.name), out)
    for ex in new.executors:
        try:
            before = old.executor(ex.name)
        except KeyError:
            continue  # a new executor joins when it starts and registers
        for f in fields(ex):
            if f.name not in LIVE_EXECUTOR_FIELDS:
                _differences(f"executors.{ex.name}.{f.name}", getattr(before, f.name), getattr(ex, f.name), out)
    return out


def desired_models(cfg: ClusterConfig, executor: str, serving: Iterable[str]) -> list[str] | None:
    """The models ``executor`` should serve under ``cfg``: its own list, or for a replica outside the config (scaled
    out beside it) the models it serves that ``cfg`` still defines, at ``cfg``'s settings; left alone, it would
    serve old weights or deadlines beside executors on the new ones. None: nothing to change (a replica with none)."""
    try:
        return cfg.executor(executor).models
    except KeyError:
        defined = {m.name for m in cfg.models}
        return [m for m in sorted(serving) if m in defined] or None


def plan_steps(old: ClusterConfig, new: ClusterConfig, state: ClusterState) -> list[Step]:
    """The executors (registered now) whose hosted models or model settings differ in ``new``."""
    steps: list[tuple[int, int, Step]] = []
    for name, ex in state.executors.items():
        wanted = desired_models(new, name, ex.models)
        if wanted is None:
            continue
        current = set(ex.models)

        def changed(model: str) -> bool:
            try:
                # A change of settings only the traffic controller reads (populations) re-solves the quotas
                # without reloading the executors hosting the model. What the executor registered is compared
                # where it said: after a failed step it still runs settings the file before this one no longer
                # names, and applying the same file again must retry it.
                if ex.settings is not None and model in ex.settings:
                    return ex.settings[model] != settings_digest(new.model(model))
                return executor_settings(old.model(model)) != executor_settings(new.model(model))
            except KeyError:
                return True

        if set(wanted) == current and not any(changed(m) for m in wanted):
            continue
        added, removed = len(set(wanted) - current), len(current - set(wanted))
        steps.append((-added, removed, Step(name, [new.model(m) for m in wanted])))
    pending = [s for _, _, s in sorted(steps, key=lambda t: (t[0], t[1], t[2].executor))]
    # A step drains its executor for the whole reload. Each next step is the first (gainers first) whose
    # executor's models all have another serving host at that point; only where none has (a swap of two
    # single-hosted models) does a model go without a host, and the step names it.
    serving = _serving(state)
    defined = {m.name for m in new.models}

    def unhosted(step: Step) -> list[str]:
        # A model the new config no longer defines is retired, not left without a host.
        return sorted(_only_host(serving, step.executor, serving.get(step.executor, set())) & defined)

    ordered: list[Step] = []
    while pending:
        step = next((s for s in pending if not unhosted(s)), pending[0])
        step.unhosted = unhosted(step)
        pending.remove(step)
        if step.executor in serving:
            serving[step.executor] = {m.name for m in step.models}
        ordered.append(step)
    hosted_at_end = set().union(*serving.values())
    for step in ordered:
        step.awaits = [m for m in step.unhosted if m not in hosted_at_end]
        step.unhosted = [m for m in step.unhosted if m in hosted_at_end]
    return ordered


def _serving(state: ClusterState) -> dict[str, set[str]]:
    """The models each executor routed now serves."""
    return {name: set(ex.models) for name, ex in state.executors.items() if not state.routed_nothing_new(name)}


def _only_host(serving: dict[str, set[str]], executor: str, models: Iterable[str]) -> set[str]:
    """Those of ``models`` that no executor of ``serving`` but ``executor`` serves."""
    others = set().union(*(ms for n, ms in serving.items() if n != executor))
    return set(models) - others


def _drain(state: ClusterState, step: Step) -> None:
    """Route nothing new to the step's executor; its load goes out once the router routes by
    this table (``drained_version``)."""
    state.set_draining(step.executor, True)
    step.drained_version = state.table.version


# How long a step whose dropped models have no other host yet waits for one, from when its turn comes: long enough
# for an executor started after the apply to start (on a GPU its graphs and profile take minutes), and its old host
# serves them meanwhile.
HOST_WAIT_S = 300.0


class Rollout:
    def __init__(self, steps: list[Step], timeout_s: float = 600.0, gone_s: float = 30.0,
                 host_wait_s: float = HOST_WAIT_S):
        self.pending = list(steps)
        self.timeout_s = timeout_s
        # How long a step whose dropped models have no other host yet (Step.awaits) waits for one.
        self.host_wait_s = host_wait_s
        # An executor that is off the registry this long during its change (it died or lost the
        # control plane while reloading) fails its step, instead of the rollout waiting out timeout_s.
        self.gone_s = gone_s
        self._gone_since: float | None = None
        self.done_steps: list[str] = []
        self.failed: list[str] = []
        # Names this rollout in `status`: `robion ctl apply` waits for its own, and can tell it from one a restarted
        # control plane (which forgot it) or a later reconcile shows.
        self.id = uuid.uuid4().hex[:12]

    @property
    def current(self) -> Step | None:
        return self.pending[0] if self.pending else None

    @property
    def finished(self) -> bool:
        return not self.pending

    def tick(self, state: ClusterState, send_load: SendLoad, now: float | None = None) -> None:
        now = now or time.monotonic()
        step = self.current
        if step is None:
            return
        if not step.started:
            if step.executor not in state.executors:
                # Off the registry for a moment (missed heartbeats, a restart) is not gone: it gets the grace a
                # started step gets.
                if self._gone(now) > self.gone_s:
                    log.error("executor %s is off the registry (for %.0f s); skipping its placement change",
                              step.executor, self._gone(now))
                    self._skip(step)
                return
            self._gone_since = None
            # What the executor serves now, as plan_steps counted it (nothing while an operator drains it), of the
            # models the desired config still defines: dropping a retired model loses no host it needs.
            serving = _serving(state)
            only = _only_host(serving, step.executor, serving.get(step.executor, set()))
            defined = {m.name for m in state.cfg.models}
            lost = sorted((only & defined) - {m.name for m in step.models} - set(step.unhosted))
            if lost and set(lost) <= set(step.awaits):
                if not step.waiting_since:
                    step.waiting_since = now
                    log.warning("placement change: %s drops %s once another executor serves them; waiting up to "
                                "%.0f s for one (their new hosts are not registered or are drained)", step.executor,
                                lost, self.host_wait_s)
                if now - step.waiting_since <= self.host_wait_s:
                    # A host of theirs that came back meanwhile with other models (restarted, reading its old file)
                    # had its reload queued behind this step: it goes first, or the wait could only run out.
                    ahead = next((s for s in self.pending[1:] if set(lost) & {m.name for m in s.models}), None)
                    if ahead is not None:
                        self.pending.remove(ahead)
                        self.pending.insert(0, ahead)
                        # A swap: what it drops as the only host, this step takes over once it runs. Left without a
                        # host for the two reloads (as plan_steps names a swap's models), not a reason to fail it.
                        ahead_serves = serving.get(ahead.executor, set())
                        swapped = (_only_host(serving, ahead.executor, ahead_serves) & defined
                                   & {m.name for m in step.models}) - {m.name for m in ahead.models}
                        ahead.unhosted = sorted(set(ahead.unhosted) | swapped)
                        # The wait keeps its clock: a reload that fails gives the host no second 300 s.
                        log.info("placement change: %s goes before %s, which waits for it to serve %s",
                                 ahead.executor, step.executor, lost)
                    return
                log.error("executor %s is the only host of %s, which its placement change drops, and no other "
                          "executor serves them after %.0f s (start or resume their new hosts, then apply again); "
                          "keeping %s as it is", step.executor, lost, self.host_wait_s, step.executor)
                self._skip(step)
                return
            if lost:
                # The plan counted on another executor serving these by now; its step failed (or it left). Dropping
                # them here would leave them with no host at all, not just for this reload.
                log.error("executor %s is the only host of %s, which its placement change drops: an earlier step "
                          "that was to host them elsewhere did not; keeping %s as it is", step.executor, lost,
                          step.executor)
                self._skip(step)
                return
            step.started = now
            _drain(state, step)
            return
        if step.executor in state.executors:
            self._gone_since = None
        if step.executor not in state.executors and self._gone(now) > self.gone_s:
            log.error("executor %s left during its placement change (off the registry for %.0f s); skipping it",
                      step.executor, self._gone(now))
            self._skip(step)
            return
        if not step.loading and step.executor in state.executors and state.router_version >= step.drained_version:
            # Only once the router routes by the drained table can no new request reach the executor
            # (and a load sent while it is off the registry would be dropped by the socket).
            step.loading = True
            step.instance = state.executors[step.executor].instance
            step.load_id = uuid.uuid4().hex
            send_load(step.executor, step.models, step.load_id)
            log.info("placement change: %s drained, loading %s", step.executor, [m.name for m in step.models])
        elif now - step.started > self.timeout_s:
            log.error("executor %s did not reload within %.0f s; resuming it as it is", step.executor, self.timeout_s)
            state.set_draining(step.executor, False)
            self._skip(step)

    def _skip(self, step: Step) -> None:
        self.failed.append(step.executor)
        self.pending.pop(0)
        self._gone_since = None

    def _gone(self, now: float) -> float:
        """Seconds the current step's executor has been off the registry (counted from the first tick
        that saw it gone); the tick that sees it back resets the count."""
        if self._gone_since is None:
            self._gone_since = now
        return now - self._gone_since

    def on_register(self, state: ClusterState, executor: str, models: list[str], load: dict | None = None) -> None:
        """``load``: the outcome of the executor's last reload, {id, ok, error?}, as its registration carries it."""
        step = self.current
        if step is None or step.executor != executor or not step.started:
            return
        ex = state.executors.get(executor)
        if step.loading and isinstance(load, dict) and load.get("id") == step.load_id:
            state.set_draining(executor, False)
            if load.get("ok") is True:
                log.info("placement change: %s serves %s again (table v%d)", executor, sorted(models),
                         state.table.version)
                self.done_steps.append(executor)
                self.pending.pop(0)
            else:
                # It kept (or went back to) its previous models: waiting for the step's timeout would keep it
                # out of routing (and every `apply` BUSY) meanwhile.
                log.error("executor %s could not load %s (%s) and serves %s again; resuming it, its placement "
                          "change failed", executor, [m.name for m in step.models], load.get("error", "see its log"),
                          sorted(models))
                self._skip(step)
            return
        if step.loading and ex is not None and step.instance and ex.instance != step.instance:
            # A new process with its old model set: the executor restarted and never got (or
            # lost) the load. Drain it again and send the load again, as at the step's start.
            log.warning("executor %s restarted during its placement change; loading %s again", executor,
                        [m.name for m in step.models])
            step.loading = False
            _drain(state, step)
            return
        if ex is not None and not ex.draining:
            # Back after it was off the registry (missed heartbeats): its new registry entry is routed.
            # It stays drained for its whole step, and a load not yet sent waits until the router
            # routes by this drained table again.
            log.warning("executor %s registered again during its placement change; draining it again", executor)
            _drain(state, step)
        # Otherwise the same process re-registering while it reloads (it lost the control plane): keep waiting.

    def status(self) -> dict:
        return {"id": self.id, "pending": [s.executor for s in self.pending], "done": self.done_steps,
                "failed": self.failed, "current": self.current.executor if self.current and self.current.started else None}
