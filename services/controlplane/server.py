"""The control plane's socket loop: registrations, heartbeats, routing tables, status."""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import asdict
from typing import Any

import zmq

from services.controlplane.rollout import (LIVE_CONTROL_FIELDS, Rollout, Step, desired_models, plan_steps,
                                           restart_only_changes)
from services.controlplane.state import ClusterState
from shared import control
from shared.config import ClusterConfig, ConfigError, ModelConfig, config_from_dict, parse_yaml, settings_digest
from shared.control import ControlError
from shared.metrics import ControlMetrics, serve
from shared.protocol import ModelInfo, ProtocolError, shown
from shared.service import bind

log = logging.getLogger("robion.control")


class BadRequest(Exception):
    """A control message the plane cannot act on: answered BAD_REQUEST, naming the field."""


def _kind_of(value: Any) -> str:
    return "nothing" if value is None else type(value).__name__


def _name(msg: dict, field: str) -> str:
    """A required executor name: a non-empty string (str() of anything else would make up a name)."""
    value = msg.get(field)
    if not isinstance(value, str) or not value:
        raise BadRequest(f"{field}: expected a non-empty string, got {_kind_of(value)}")
    return value


def _mapping(msg: dict, field: str, required: bool = False) -> dict:
    """A map field; an optional one may be absent or null (read as empty)."""
    value = msg.get(field)
    if value is None and not required:
        return {}
    if not isinstance(value, dict):
        raise BadRequest(f"{field}: expected a map, got {_kind_of(value)}")
    return value


class ControlPlane:
    KINDS = ("register", "heartbeat", "deregister", "table_get", "status", "apply", "drain", "resume")
    ANSWERED = ("register", "table_get", "status")  # besides apply, drain and resume (see _admin)

    def __init__(self, cfg: ClusterConfig, context: zmq.Context | None = None):
        self.cfg = cfg
        self.state = ClusterState(cfg)
        self.ctx = context or zmq.Context.instance()
        self.sock = self.ctx.socket(zmq.ROUTER)
        self.sock.setsockopt(zmq.LINGER, 0)
        # Executors connect with their name as identity. Without handover, libzmq ignores a new connection
        # whose identity an open one holds (a hung old process, or a half-open TCP connection left by a
        # crashed host), for as long as the new one lives: the restarted executor's registrations and
        # heartbeats were dropped unread, and it never rejoined routing.
        self.sock.setsockopt(zmq.ROUTER_HANDOVER, 1)
        bind(self.sock, cfg.control.bind, "control.bind")
        self.metrics = ControlMetrics()
        serve(self.metrics.registry, cfg.control.metrics_port)
        self._published: set[str] = set()
        self._assigned: set[tuple[str, str]] = set()
        self.rollout: Rollout | None = None
        # The last apply's rollout, kept after a reconcile's takes its place: `status` reports it as `apply`.
        self.applied_rollout: Rollout | None = None
        # Whether an `apply` changed the desired state in this process's lifetime (see _reconcile), and the
        # process of each configured executor already checked against it.
        self.applied = False
        self._reconciled: dict[str, str] = {}

    def run(self, stop: threading.Event) -> None:
        # When the socket was last seen empty: every heartbeat sent before then has been read. Heartbeat
        # ages are measured at that moment, not at the tick: a round that ends at its message cap right
        # after a multi-second solve leaves live executors' heartbeats queued, and measuring at the tick
        # expired them, their re-registrations solved again, and so on (a storm). While the plane is
        # behind, nothing expires; the round that catches up judges every executor on what it sent.
        drained = time.monotonic()
        while not stop.is_set():
            if not self.sock.poll(100):
                drained = time.monotonic()
            else:
                for _ in range(256):
                    try:
                        frames = self.sock.recv_multipart(zmq.NOBLOCK)
                    except zmq.Again:
                        drained = time.monotonic()
                        break
                    try:
                        self._handle(frames)
                    except Exception:
                        log.exception("bad control message")
            try:
                self._tick(drained)
            except Exception:
                # An unforeseen failure in the periodic work (the re-plan after an expiry, a
                # rollout step, metrics) must not end the control plane: routers and executors
                # depend on it. The work runs again on the next tick.
                log.exception("periodic control-plane work failed")
        self.sock.close(linger=0)

    def _tick(self, drained: float | None = None) -> None:
        """Periodic work; ``drained``: when the socket was last seen empty (heartbeat ages are measured then)."""
        for name in self.state.expire(drained):
            log.warning("executor %s missed its heartbeats: removed from routing", name)
        if self.rollout is not None:
            self.rollout.tick(self.state, self._send_load)
        self._update_metrics()

    def _update_metrics(self) -> None:
        live = set(self.state.executors)
        # A configured executor that is down reads 0. A replica outside the config registers under a name of
        # its own (docker-compose: its container's), new with every scale-out or redeploy: its series go once
        # it has left, or they would pile up in this process and in Prometheus for good.
        # A configured executor that never registered with this process (down since before a restart, never
        # started) reads 0 too: an alert on executor_up == 0 must see it.
        configured = {e.name for e in self.state.cfg.executors}
        for name in (self._published | configured) - live:
            if name in configured:
                self.metrics.executor_up.labels(name).set(0)
                self._published.add(name)
            else:
                self.metrics.executor_up.remove(name)
                self._published.discard(name)
        for name in live:
            self.metrics.executor_up.labels(name).set(1)
        self._published |= live
        self.metrics.executors.set(len(live))
        quotas = self.state.table.quotas
        for model, per in quotas.items():
            for ex, n in per.items():
                self.metrics.robots_assigned.labels(model, ex).set(n)
        published = {(m, e) for m, per in quotas.items() for e in per}
        populated = {m.name for m in self.state.cfg.models if m.robots > 0}
        placed = {(m, e.name) for e in self.state.cfg.executors for m in e.models if m in populated}
        for model, ex in (self._assigned | placed) - published:
            if ex in configured and model in populated:
                self.metrics.robots_assigned.labels(model, ex).set(0)
                published.add((model, ex))  # kept (at 0) until the config drops the executor or the model
            else:
                self.metrics.robots_assigned.remove(model, ex)
        self._assigned = published
        self.metrics.table_version.set(self.state.table.version)

    def _reconcile(self, name: str, instance: str, settings: dict | None) -> None:
        """Bring a (re)started executor to the desired state an `apply` made.

        A process loads the models of its own config file as it starts. An executor that restarted after an
        apply (a crash, a supervisor's restart), or was down when it ran, came back with the placement and
        settings from before it, and nothing told it otherwise. Once per process, its registered settings
        (a digest per model) are compared with the desired state, and a reload is queued where they differ.
        Without an apply in this control plane's lifetime its desired state is the file the executors read
        too: after a restart of the plane, pushing that would undo an apply the executors still run.
        """
        st = self.state
        if not self.applied or settings is None or self._reconciled.get(name) == instance:
            return
        wanted = desired_models(st.cfg, name, settings)
        if wanted is None:
            return
        self._reconciled[name] = instance
        if settings == {m: settings_digest(st.cfg.model(m)) for m in wanted}:
            return
        if self.rollout is not None and any(s.executor == name for s in self.rollout.pending):
            return  # its step of the running rollout brings it there
        step = Step(name, [st.cfg.model(m) for m in wanted])
        log.warning("executor %s registered models or settings other than the applied ones: reloading it with %s",
                    name, wanted)
        if self.rollout is None or self.rollout.finished:
            self.rollout = Rollout([step])
        else:
            self.rollout.pending.append(step)

    def _drift(self) -> dict[str, dict]:
        """Executors whose registered models or settings are not what this plane's desired state says: after a
        restart of the plane (it knows only its file, and applies nothing until an apply of its own) status read
        `ready` while executors served an earlier apply's placement, and nothing showed it."""
        st, out = self.state, {}
        for name, ex in st.executors.items():
            wanted = desired_models(st.cfg, name, ex.models)
            if wanted is None:
                continue
            differ = sorted(m for m in wanted if ex.settings is not None and m in ex.settings
                            and ex.settings[m] != settings_digest(st.cfg.model(m)))
            if set(wanted) != set(ex.models) or differ:
                out[name] = {"serves": sorted(ex.models), "desired": sorted(wanted), "settings_differ": differ}
        return out

    def _send_load(self, executor: str, models: list[ModelConfig], load_id: str) -> None:
        self.sock.send_multipart([executor.encode(), control.pack("load", models=[asdict(m) for m in models],
                                                                  load_id=load_id)])

    def _reply(self, peer: bytes, kind: str, **fields) -> None:
        self.sock.send_multipart([peer, control.pack(kind, **fields)])

    def _error(self, peer: bytes, code: ControlError, message: str) -> None:
        self.sock.send_multipart([peer, control.error(code, message)])

    def _admin(self, peer: bytes, kind: str, msg: dict) -> None:
        """An operator's apply, drain or resume: always answered, so `robion ctl` never waits in vain.

        A failure that the checks below do not foresee is logged with its traceback and sent back as an
        error (the CLI prints it and exits 1); the control plane keeps serving.
        """
        try:
            self._admin_request(peer, kind, msg)
        except BadRequest:
            raise  # answered BAD_REQUEST by _handle
        except Exception as exc:
            log.exception("%s failed", kind)
            self._error(peer, ControlError.INTERNAL, f"{kind} failed on the control plane: {type(exc).__name__}: "
                        f"{exc} (see the control plane's log)")

    def _admin_request(self, peer: bytes, kind: str, msg: dict) -> None:
        st = self.state
        if kind == "apply":
            if self.rollout is not None and not self.rollout.finished:
                return self._error(peer, ControlError.BUSY,
                                   f"a placement change is in progress: {self.rollout.status()}")
            text = msg.get("config")
            if not isinstance(text, str):
                # str() of anything else would be parsed as YAML and blamed on the operator's file.
                raise BadRequest(f"config: expected the config file's text (a string), got {_kind_of(text)}")
            try:
                raw = parse_yaml(text)
            except ConfigError as exc:
                return self._error(peer, ControlError.BAD_CONFIG, f"config error: the applied file: {exc}")
            # A change of imports is refused below anyway (restart only): decided before the new modules would be
            # imported, so their code never runs in this process for an apply that changes nothing.
            imports = raw.get("imports", []) if isinstance(raw, dict) else []
            if isinstance(imports, list) and all(isinstance(n, str) for n in imports) and imports != st.cfg.imports:
                return self._error(peer, ControlError.RESTART_REQUIRED, "imports take effect only on restart, so "
                                   f"nothing was changed: imports: {st.cfg.imports!r} -> {imports!r}")
            try:
                new = config_from_dict(raw)
            except ConfigError as exc:
                return self._error(peer, ControlError.BAD_CONFIG, f"config error: {exc}")
            fixed = restart_only_changes(st.cfg, new)
            if fixed:
                live = ", ".join(["models", "executors' models and memory_gb"]
                                 + [f"control.{f}" for f in sorted(LIVE_CONTROL_FIELDS)])
                return self._error(peer, ControlError.RESTART_REQUIRED, f"apply changes {live} live; these "
                                   "settings take effect only on restart, so nothing was changed: " + "; ".join(fixed))
            steps = plan_steps(st.cfg, new, st)
            st.replace_config(new)
            st.settle()
            self.applied = True
            # The processes registered now are this apply's to change (its steps); _reconcile takes those
            # that start or come back later. Checked again, a failed step's executor would be retried at once.
            self._reconciled = {name: ex.instance for name, ex in st.executors.items()}
            self.rollout = self.applied_rollout = Rollout(steps)
            log.info("apply: new desired state, table v%d; executors to reload: %s", st.table.version,
                     [s.executor for s in steps])
            unhosted = {s.executor: s.unhosted for s in steps if s.unhosted}
            for name, models in unhosted.items():
                log.warning("apply: while %s reloads no other executor serves %s: their requests are answered "
                            "UNAVAILABLE until it is back", name, models)
            awaiting = {s.executor: s.awaits for s in steps if s.awaits}
            for name, models in awaiting.items():
                log.warning("apply: %s drops %s only once another executor serves them, and none registered and "
                            "routed is to: its step waits up to %.0f s for their new hosts to start or be resumed, "
                            "then fails", name, models, self.rollout.host_wait_s)
            return self._reply(peer, "applied", steps=[s.executor for s in steps], version=st.table.version,
                               unhosted=unhosted, awaiting=awaiting, host_wait_s=self.rollout.host_wait_s,
                               rollout=self.rollout.id)
        name = _name(msg, "executor")
        if kind == "drain" and peer == name.encode():
            # The executor drains itself as it shuts down (ExecutorIO.withdraw; its control socket's identity
            # is its name). That drain belongs to this process's registry entry, as a placement change's does:
            # kept by name as an operator's is, the next process under the name would come back drained.
            ok = st.set_draining(name, True)
        else:
            ok = st.set_drained(name, kind == "drain")
        if not ok:
            return self._error(peer, ControlError.UNKNOWN_EXECUTOR, f"no executor named {name!r} is registered")
        st.settle()
        log.info("%s %s (table v%d)", "drained" if kind == "drain" else "resumed", name, st.table.version)
        # What the drain leaves with no route at all (it was their only host), for the operator to hear at once.
        unrouted = sorted(m for m in st.executors[name].models if not st.table.routes.get(m)) if kind == "drain" else []
        self._reply(peer, "ok", version=st.table.version, unrouted=unrouted)

    def _handle(self, frames: list[bytes]) -> None:
        peer, body = frames[0], frames[-1]
        try:
            msg = control.unpack(body)
        except ProtocolError as exc:
            self._error(peer, ControlError(exc.code.value), exc.message)
            return
        kind = msg.get("kind")
        if kind not in self.KINDS:
            self._error(peer, ControlError.BAD_REQUEST, f"unknown kind {shown(kind)}")
            return
        try:
            self._dispatch(peer, kind, msg)
        except BadRequest as exc:
            # Answered, so the sender learns at once what to fix rather than waiting out its timeout.
            log.warning("bad %s message: %s", kind, exc)
            self._error(peer, ControlError.BAD_REQUEST, f"{kind}: {exc}")
        except Exception as exc:
            if kind not in self.ANSWERED:
                raise  # heartbeat and deregister are never answered: logged by run()
            # The sender waits for a reply: tell it the plane failed instead of letting it time out.
            log.exception("%s failed", kind)
            self._error(peer, ControlError.INTERNAL, f"{kind} failed on the control plane: {type(exc).__name__}: "
                        f"{exc} (see the control plane's log)")

    def _dispatch(self, peer: bytes, kind: Any, msg: dict) -> None:
        """Every field is checked before anything changes, so a refused message leaves no trace."""
        st = self.state
        if kind == "register":
            name = _name(msg, "executor")
            models: dict[str, ModelInfo] = {}
            for model, info in _mapping(msg, "models", required=True).items():
                try:
                    models[str(model)] = ModelInfo.from_wire(info)
                except ValueError as exc:
                    raise BadRequest(f"models.{model}: malformed model description ({exc})") from None
                try:
                    # The description goes into every routing table and status (and outlives this
                    # executor): one msgpack cannot pack (int(1e30) as a state_dim) would leave all of
                    # them unanswered from now on.
                    control.pack("model", info=models[str(model)].to_wire())
                except (OverflowError, TypeError, ValueError) as exc:
                    raise BadRequest(f"models.{model}: a value of the model description cannot be sent "
                                     f"on ({type(exc).__name__}: {exc})") from None
            # Each limit's value is checked by ClusterState.register: a bad one is ignored, not fatal.
            limits = {str(m): c for m, c in _mapping(msg, "limits").items()}
            instance = msg.get("instance", "")
            if not isinstance(instance, str):
                raise BadRequest(f"instance: expected a string, got {_kind_of(instance)}")
            load = msg.get("load")
            if load is not None and not isinstance(load, dict):
                raise BadRequest(f"load: expected a map, got {_kind_of(load)}")
            settings = msg.get("settings")
            if settings is not None and not isinstance(settings, dict):
                raise BadRequest(f"settings: expected a map, got {_kind_of(settings)}")
            digests = {str(m): d for m, d in settings.items() if isinstance(d, str)} if settings is not None else None
            st.register(name, str(msg.get("device", "")), models, limits=limits, instance=instance, settings=digests)
            log.info("executor %s registered on %s with %s (table v%d)", name, msg.get("device"),
                     sorted(models), st.table.version)
            if self.rollout is not None:
                self.rollout.on_register(st, name, list(models), load)
            self._reconcile(name, instance, settings)
            self._reply(peer, "registered", version=st.table.version)
        elif kind == "heartbeat":
            depths = _mapping(msg, "depths")
            # Kept for `status`: one value status cannot pack (nested a thousand deep, an int beyond 64 bits)
            # would fail every status from then on, and with it executors' withdrawals and `apply --wait`.
            bad = next((m for m, d in depths.items() if not isinstance(m, str) or isinstance(d, bool)
                        or not isinstance(d, int) or not 0 <= d < 1 << 63), None)
            if bad is not None:
                raise BadRequest(f"depths.{shown(bad)}: expected a non-negative integer queue depth per model name")
            known = st.heartbeat(_name(msg, "executor"), dict(depths))
            if not known:
                self._reply(peer, "reregister")
        elif kind == "deregister":
            name = _name(msg, "executor")
            st.deregister(name)
            log.info("executor %s left (table v%d)", name, st.table.version)
        elif kind == "table_get":
            # The router reports the version it routes by; ``ready`` and rollouts compare it with ours.
            version = msg.get("version", -1)
            if isinstance(version, bool) or not isinstance(version, int):
                raise BadRequest(f"version: expected an integer, got {_kind_of(version)}")
            if msg.get("role") == "router":
                st.router_seen = time.monotonic()
                st.router_version = version
                st.hear_router(version, msg.get("executors"))
            # While the plane settles (state.SETTLE_HEARTBEATS) it has no table to offer: a router keeps the
            # one it routes by, and the executors it routes to register again meanwhile.
            newer = version != st.table.version and st.settled()
            self._reply(peer, "table", table=st.table.to_wire() if newer else None)
        elif kind == "status":
            status = st.status()
            status["rollout"] = self.rollout.status() if self.rollout is not None else None
            status["apply"] = self.applied_rollout.status() if self.applied_rollout is not None else None
            status["drift"] = self._drift()
            self._reply(peer, "status", status=status)
        else:  # apply, drain, resume
            self._admin(peer, kind, msg)
