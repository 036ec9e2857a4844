"""Starting a whole Robion cluster as local processes, waiting for it, and stopping it cleanly."""

from __future__ import annotations

import logging
import math
import os
import signal
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


def metrics_port_clash(cfg: ClusterConfig) -> str | None:
    """Why the services of ``cfg`` cannot all serve metrics on one host, if they cannot: two given one port (an
    executor's ``metrics_port`` equal to another's default 9110 + index, the router's and the control plane's).
    The second to bind only logs a failure, and Prometheus then scrapes the first under the second's target."""
    owners: dict[int, str] = {}
    ports = [("the router", cfg.router.metrics_port), ("the control plane", cfg.control.metrics_port)]
    ports += [(f"executor {ex.name}", ex.metrics_port_or_default(i)) for i, ex in enumerate(cfg.executors)]
    for who, port in ports:
        if port and port in owners:
            return (f"metrics port {port} is both {owners[port]}'s and {who}'s on this host; give one another "
                    f"metrics_port (executors default to 9110 + their index; 0 disables)")
        owners[port] = who
    return None


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


class LocalCluster:
    """Control plane, router and one process per executor, all children of this process."""

    def __init__(self, cfg: ClusterConfig, config_path: str | Path, log_level: str = "INFO"):
        self.cfg = cfg
        self.config_path = str(config_path)
        self.log_level = log_level
        self.procs: dict[str, subprocess.Popen] = {}

    def _spawn(self, name: str, module: str, *extra: str) -> None:
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

    def alive(self) -> dict[str, bool]:
        return {name: p.poll() is None for name, p in self.procs.items()}

    def stop(self, grace_s: float = 10.0) -> dict[str, int]:
        """Stop executors first (their last replies still pass the router), then router and control plane.

        Each gets SIGTERM and ``grace_s`` to finish; stragglers are killed, so nothing outlives us.
        """
        codes: dict[str, int] = {}
        executors = [n for n in self.procs if n.startswith("executor")]
        for wave in (executors, ["router"], ["control"]):
            procs = {n: self.procs[n] for n in wave if n in self.procs}
            for p in procs.values():
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
            end = time.monotonic() + grace_s
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
