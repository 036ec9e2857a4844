"""Starting a whole Robion cluster as local processes, waiting for it, and stopping it cleanly."""

from __future__ import annotations

import logging
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import zmq

from shared import control
from shared.config import ClusterConfig, ConfigError, bound_addresses, dial_address, positive_number
from shared.service import bind, connect

log = logging.getLogger("robion.cluster")


def control_request(address: str, kind: str, timeout_s: float = 1.0, context: zmq.Context | None = None,
                    **fields) -> dict | None:
    """One request to the control plane's admin API; None when it does not answer in time.

    ``timeout_s`` must be positive and finite: zmq's poll() waits forever on a negative timeout
    and does not wait at all on zero, so either would hide a control plane that does not answer.
    """
    if not positive_number(timeout_s):
        raise ValueError(f"timeout_s must be a positive number of seconds, got {timeout_s!r}")
    ctx = context or zmq.Context.instance()
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    try:
        connect(sock, address)
        sock.send(control.pack(kind, **fields))
        if not sock.poll(math.ceil(timeout_s * 1000)):  # ceil: a sub-millisecond timeout still waits
            return None
        return control.unpack(sock.recv())
    finally:
        sock.close()


def control_status(address: str, timeout_s: float = 1.0, context: zmq.Context | None = None) -> dict | None:
    """Ask the control plane for its status; None when it does not answer in time."""
    reply = control_request(address, "status", timeout_s, context)
    return reply.get("status") if reply else None


def _metrics_ports(cfg: ClusterConfig) -> list[tuple[str, int]]:
    """(whose, port) of every service's metrics port in ``cfg``; 0 is a service that serves none."""
    ports = [("the router", cfg.router.metrics_port), ("the control plane", cfg.control.metrics_port)]
    return ports + [(f"executor {ex.name}", ex.metrics_port_or_default(i)) for i, ex in enumerate(cfg.executors)]


def metrics_port_clash(cfg: ClusterConfig) -> str | None:
    """Why the services of ``cfg`` cannot all serve metrics on one host, if they cannot: two given one port (an
    executor's ``metrics_port`` equal to another's default 9110 + index, the router's and the control plane's).
    The second to bind only logs a failure, and Prometheus then scrapes the first under the second's target."""
    owners: dict[int, str] = {}
    # The ZeroMQ addresses' TCP ports too: a metrics port equal to router.backend's was taken by the router's own
    # metrics server first, and its bind then failed as "address in use", which blamed the backend address.
    for key, address in bound_addresses(cfg):
        port = address.rsplit(":", 1)[1] if address.startswith("tcp://") else ""
        if port.isdigit():
            owners[int(port)] = key
    for who, port in _metrics_ports(cfg):
        if port and port in owners:
            return (f"metrics port {port} is both {owners[port]}'s and {who}'s on this host; give one another "
                    f"metrics_port (executors default to 9110 + their index; 0 disables)")
        owners[port] = who
    return None


def metrics_ports_taken(cfg: ClusterConfig) -> list[str]:
    """Metrics ports of ``cfg`` that another process on this host holds, one line each. A service that cannot bind
    its port only logs it, so a second cluster on the first one's default ports started without metrics, and
    Prometheus scraped the first cluster's numbers under the second's targets. `robion up` warns of them rather than
    refusing: 9100, the router's default, is also node_exporter's, and metrics are not what robots need."""
    problems = []
    for who, port in _metrics_ports(cfg):
        if not port:
            continue
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
            # As the metrics server binds it (0.0.0.0, address reuse on): a port in TIME_WAIT is free to it.
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind(("0.0.0.0", port))
            except OSError as exc:
                problems.append(f"metrics port {port} ({who}'s) is taken on this host ({exc.strerror})")
    return problems


def addresses_taken(cfg: ClusterConfig) -> list[str]:
    """Why the router or control plane could not bind their TCP addresses of ``cfg``, one line each. With another
    cluster on them, its control plane answered this one's start-up poll "ready" before this one's services had even
    failed to bind, and this one's executors then registered with it. (ipc:// is not tried: binding an ipc path
    takes it from whoever holds it.)"""
    ctx = zmq.Context.instance()
    problems = []
    for key, address in bound_addresses(cfg):
        if not address.startswith("tcp://"):
            continue
        sock = ctx.socket(zmq.ROUTER)
        sock.setsockopt(zmq.LINGER, 0)
        try:
            bind(sock, address, key)
        except ConfigError as exc:  # bind() has closed the socket
            problems.append(str(exc))
        else:
            sock.close()
    return problems


# An executor's stop takes up to about 30 s: its drain waits for the control plane's traffic solve (at most 20 s) and
# answer (1 s), then for the router's switch (3 s) and its last answers (5 s). Killed after 10 s, one with a slow solve
# lost the answers it was finishing. docker-compose's stop_grace_period for executors is 40 s too.
EXECUTOR_STOP_GRACE_S = 40.0

# Exit codes after which `robion up` does not start a service again: 0 is a clean stop (SIGTERM), 2 a refusal of its
# configuration, device or models, which a restart would meet again (README, "How it fits together").
NO_RESTART_CODES = (0, 2)


class RestartPolicy:
    """When `robion up` starts a service that failed again: docker-compose's ``restart: on-failure``, with a back-off
    and a limit, and without restarting exit code 2 (which compose restarts). A crashed executor is otherwise gone for
    good under `up` (a failed reload that leaves it nothing to serve exits 1 expressly for its supervisor), and the
    router and control plane are built to be restarted: robots and executors reconnect, executors register again.

    The n-th failure of a name within ``window_s`` waits ``backoff_s[n-1]`` (the last entry from then on) before its
    restart; failure ``max_restarts + 1`` within the window is not restarted, so a service that cannot start does not
    loop for ever. ``max_restarts`` 0 restarts nothing."""

    def __init__(self, max_restarts: int = 5, window_s: float = 300.0,
                 backoff_s: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0, 16.0, 30.0)):
        if max_restarts < 0 or window_s <= 0 or not backoff_s:
            raise ValueError("max_restarts >= 0, window_s > 0 and at least one back-off step")
        self.max_restarts = max_restarts
        self.window_s = window_s
        self.backoff_s = backoff_s
        self._failures: dict[str, list[float]] = {}

    def after_exit(self, name: str, code: int, now: float) -> tuple[float | None, str]:
        """Seconds to wait before starting ``name`` again (None: leave it down), and why, for the operator."""
        if code in NO_RESTART_CODES:
            return None, ("stopped cleanly" if code == 0 else "refused its configuration, device or models") + ", not restarted"
        recent = [t for t in self._failures.get(name, []) if now - t < self.window_s] + [now]
        self._failures[name] = recent
        if len(recent) > self.max_restarts:
            if self.max_restarts == 0:
                return None, "not restarted (restarts are off)"
            return None, (f"failure {len(recent)} within {self.window_s:g} s, more than the {self.max_restarts} "
                          "restarts allowed: not restarted")
        delay = self.backoff_s[min(len(recent), len(self.backoff_s)) - 1]
        return delay, f"starting it again in {delay:g} s (restart {len(recent)} of {self.max_restarts} within " \
                      f"{self.window_s:g} s)"


class LocalCluster:
    """Control plane, router and one process per executor, all children of this process."""

    def __init__(self, cfg: ClusterConfig, config_path: str | Path, log_level: str = "INFO"):
        self.cfg = cfg
        self.config_path = str(config_path)
        self.log_level = log_level
        self.procs: dict[str, subprocess.Popen] = {}
        self._commands: dict[str, tuple[str, ...]] = {}

    def _spawn(self, name: str, module: str, *extra: str) -> None:
        self._commands[name] = (module, *extra)
        cmd = [sys.executable, "-m", module, "--config", self.config_path, "--log-level", self.log_level,
               "--parent-pid", str(os.getpid()), *extra]
        # A session of its own: a Ctrl-C at the terminal reaches the whole foreground process group, and the
        # services would all stop at once; stop() stops them in order instead (executors first, so their last
        # replies still go out through the router). They still exit when this process is gone (--parent-pid).
        self.procs[name] = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, start_new_session=True)

    def start(self, timeout_s: float = 120.0, progress: Callable[[str], None] | None = None) -> dict:
        """Start every process and block until the control plane reports the cluster ready; ``progress`` is told
        of each executor as it registers (an engine's start takes minutes on a GPU: graph capture, profiling)."""
        clash = metrics_port_clash(self.cfg)
        if clash is not None:  # all on one host here; executors of a cluster spread over hosts may share a port
            raise RuntimeError(clash)
        taken = addresses_taken(self.cfg)
        if taken:
            raise RuntimeError(f"{'; '.join(taken)}. Is another cluster running with this config? Stop it, or give "
                               "this one other addresses")
        self._spawn("control", "services.controlplane.main")
        self._spawn("router", "services.router.main")
        for ex in self.cfg.executors:
            self._spawn(f"executor[{ex.name}]", "services.executor.main", "--name", ex.name)
        deadline = time.monotonic() + timeout_s
        registered: set[str] = set()
        while time.monotonic() < deadline:
            for name, p in self.procs.items():
                if p.poll() is not None:
                    self.stop()
                    raise RuntimeError(f"{name} exited with code {p.returncode} during start-up")
            status = control_status(dial_address(self.cfg.control.bind, self.cfg.control.connect), timeout_s=0.5)
            for name in sorted(set((status or {}).get("executors", {})) - registered):
                registered.add(name)
                if progress is not None:
                    progress(f"executor {name} is serving ({len(registered)} of {len(self.cfg.executors)})")
            if status and status.get("ready"):
                return status
            time.sleep(0.1)
        self.stop()
        raise TimeoutError(f"cluster not ready within {timeout_s:.0f} s")

    def respawn(self, name: str) -> None:
        """Start ``name`` again with the command line it had (its config file read afresh); it must have exited."""
        if self.procs[name].poll() is None:
            raise RuntimeError(f"{name} is still running")
        self._spawn(name, *self._commands[name])

    def alive(self) -> dict[str, bool]:
        return {name: p.poll() is None for name, p in self.procs.items()}

    def stop(self, grace_s: float = 10.0, executor_grace_s: float = EXECUTOR_STOP_GRACE_S) -> dict[str, int]:
        """Stop executors first (their last replies still pass the router), then router and control plane.

        Each gets SIGTERM and ``grace_s`` (executors ``executor_grace_s``) to finish; stragglers are killed, so
        nothing outlives us.
        """
        codes: dict[str, int] = {}
        executors = [n for n in self.procs if n.startswith("executor")]
        for wave, grace in ((executors, executor_grace_s), (["router"], grace_s), (["control"], grace_s)):
            procs = {n: self.procs[n] for n in wave if n in self.procs}
            for p in procs.values():
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
            end = time.monotonic() + grace
            for name, p in procs.items():
                try:
                    codes[name] = p.wait(timeout=max(0.1, end - time.monotonic()))
                except subprocess.TimeoutExpired:
                    log.warning("%s did not stop in time: killing it", name)
                    p.kill()
                    codes[name] = p.wait()
        return codes

    def __enter__(self) -> "LocalCluster":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
