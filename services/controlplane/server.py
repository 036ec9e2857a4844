"""The control plane's socket loop: registrations, heartbeats, routing tables, status."""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import asdict

import yaml
import zmq

from services.controlplane.rollout import Rollout, plan_steps, restart_only_changes
from services.controlplane.state import ClusterState
from shared import control
from shared.config import ClusterConfig, ConfigError, ModelConfig, config_from_dict
from shared.metrics import ControlMetrics, serve
from shared.protocol import ModelInfo, ProtocolError

log = logging.getLogger("robion.control")


class ControlPlane:
    def __init__(self, cfg: ClusterConfig, context: zmq.Context | None = None):
        self.cfg = cfg
        self.state = ClusterState(cfg)
        self.ctx = context or zmq.Context.instance()
        self.sock = self.ctx.socket(zmq.ROUTER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.bind(cfg.control.bind)
        self.metrics = ControlMetrics()
        serve(self.metrics.registry, cfg.control.metrics_port)
        self._published: set[str] = set()
        self._assigned: set[tuple[str, str]] = set()
        self.rollout: Rollout | None = None

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            if self.sock.poll(100):
                for _ in range(256):
                    try:
                        frames = self.sock.recv_multipart(zmq.NOBLOCK)
                    except zmq.Again:
                        break
                    try:
                        self._handle(frames)
                    except Exception:
                        log.exception("bad control message")
            try:
                self._tick()
            except Exception:
                # An unforeseen failure in the periodic work (the re-plan after an expiry, a
                # rollout step, metrics) must not end the control plane: routers and executors
                # depend on it. The work runs again on the next tick.
                log.exception("periodic control-plane work failed")
        self.sock.close(linger=0)

    def _tick(self) -> None:
        for name in self.state.expire():
            log.warning("executor %s missed its heartbeats: removed from routing", name)
        if self.rollout is not None:
            self.rollout.tick(self.state, self._send_load)
        self._update_metrics()

    def _update_metrics(self) -> None:
        live = set(self.state.executors)
        for name in self._published - live:
            self.metrics.executor_up.labels(name).set(0)
        for name in live:
            self.metrics.executor_up.labels(name).set(1)
        self._published |= live
        self.metrics.executors.set(len(live))
        quotas = self.state.table.quotas
        for model, per in quotas.items():
            for ex, n in per.items():
                self.metrics.robots_assigned.labels(model, ex).set(n)
        published = {(m, e) for m, per in quotas.items() for e in per}
        for model, ex in self._assigned - published:
            self.metrics.robots_assigned.labels(model, ex).set(0)
        self._assigned = published
        self.metrics.table_version.set(self.state.table.version)

    def _send_load(self, executor: str, models: list[ModelConfig]) -> None:
        self.sock.send_multipart([executor.encode(), control.pack("load", models=[asdict(m) for m in models])])

    def _reply(self, peer: bytes, kind: str, **fields) -> None:
        self.sock.send_multipart([peer, control.pack(kind, **fields)])

    def _admin(self, peer: bytes, kind: str, msg: dict) -> None:
        """An operator's apply, drain or resume: always answered, so `robion ctl` never waits in vain.

        A failure that the checks below do not foresee is logged with its traceback and sent back as an
        error (the CLI prints it and exits 1); the control plane keeps serving.
        """
        try:
            self._admin_request(peer, kind, msg)
        except Exception as exc:
            log.exception("%s failed", kind)
            self._reply(peer, "error", message=f"{kind} failed on the control plane: {type(exc).__name__}: {exc} "
                        "(see the control plane's log)")

    def _admin_request(self, peer: bytes, kind: str, msg: dict) -> None:
        st = self.state
        if kind == "apply":
            if self.rollout is not None and not self.rollout.finished:
                return self._reply(peer, "error", message=f"a placement change is in progress: {self.rollout.status()}")
            try:
                new = config_from_dict(yaml.safe_load(str(msg.get("config", ""))))
            except ConfigError as exc:
                return self._reply(peer, "error", message=f"config error: {exc}")
            except yaml.YAMLError:
                return self._reply(peer, "error", message="config error: not valid YAML")
            fixed = restart_only_changes(st.cfg, new)
            if fixed:
                return self._reply(peer, "error", message="apply changes models, placement, populations and "
                                   "control.strategy live; these settings take effect only on restart, so nothing "
                                   "was changed: " + "; ".join(fixed))
            steps = plan_steps(st.cfg, new, st)
            st.replace_config(new)
            self.rollout = Rollout(steps)
            log.info("apply: new desired state, table v%d; executors to reload: %s", st.table.version,
                     [s.executor for s in steps])
            return self._reply(peer, "applied", steps=[s.executor for s in steps], version=st.table.version)
        name = str(msg.get("executor", ""))
        if not st.set_draining(name, kind == "drain"):
            return self._reply(peer, "error", message=f"no executor named {name!r} is registered")
        log.info("%s %s (table v%d)", "drained" if kind == "drain" else "resumed", name, st.table.version)
        self._reply(peer, "ok", version=st.table.version)

    def _handle(self, frames: list[bytes]) -> None:
        peer, body = frames[0], frames[-1]
        try:
            msg = control.unpack(body)
        except ProtocolError as exc:
            self.sock.send_multipart([peer, control.pack("error", message=exc.message)])
            return
        kind = msg.get("kind")
        st = self.state
        if kind == "register":
            models = {n: ModelInfo.from_wire(i) for n, i in msg["models"].items()}
            limits = {str(m): int(c) for m, c in dict(msg.get("limits") or {}).items()}
            st.register(str(msg["executor"]), str(msg.get("device", "")), models, limits=limits)
            log.info("executor %s registered on %s with %s (table v%d)", msg["executor"], msg.get("device"),
                     sorted(models), st.table.version)
            if self.rollout is not None:
                self.rollout.on_register(st, str(msg["executor"]), list(models))
            self.sock.send_multipart([peer, control.pack("registered", version=st.table.version)])
        elif kind == "heartbeat":
            known = st.heartbeat(str(msg["executor"]), dict(msg.get("depths", {})))
            if not known:
                self.sock.send_multipart([peer, control.pack("reregister")])
        elif kind == "deregister":
            st.deregister(str(msg.get("executor")))
            log.info("executor %s left (table v%d)", msg.get("executor"), st.table.version)
        elif kind == "table_get":
            if msg.get("role") == "router":
                st.router_seen = time.monotonic()
                st.router_version = int(msg.get("version", -1))
            newer = msg.get("version") != st.table.version
            self.sock.send_multipart([peer, control.pack("table", table=st.table.to_wire() if newer else None)])
        elif kind == "status":
            status = st.status()
            status["rollout"] = self.rollout.status() if self.rollout is not None else None
            self.sock.send_multipart([peer, control.pack("status", status=status)])
        elif kind in ("apply", "drain", "resume"):
            self._admin(peer, kind, msg)
        else:
            self.sock.send_multipart([peer, control.pack("error", message=f"unknown kind {kind!r}")])
