"""What every service process does the same way: arguments, logging, signals, orphan guard."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from typing import Callable

import zmq
from zmq.utils.monitor import recv_monitor_message

from shared.config import ClusterConfig, ConfigError, load_config


def log_level(text: str) -> str:
    """argparse type of every --log-level: a level name in any case, upper-cased. logging.basicConfig
    raises ValueError (a traceback) on an unknown one; argparse reports it with usage and exit code 2,
    also when it comes from $ROBION_LOG_LEVEL (argparse converts a string default the same way)."""
    level = text.upper()
    if level not in logging.getLevelNamesMapping():
        names = ", ".join(n.lower() for n in ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"))
        raise argparse.ArgumentTypeError(f"expected one of {names}, got {text!r}")
    return level


def service_args(name: str, argv: list[str] | None = None, extra=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog=f"robion-{name}")
    p.add_argument("-c", "--config", required=True, help="cluster YAML config")
    p.add_argument("--log-level", type=log_level, default=os.environ.get("ROBION_LOG_LEVEL", "INFO"))
    p.add_argument("--parent-pid", type=int, default=0,
                   help="exit when this process is gone (set by `robion up`, so no service outlives it)")
    if extra:
        extra(p)
    return p.parse_args(argv)


def setup_logging(name: str, level: str) -> None:
    # The name (an executor's, from the config, --name or $HOSTNAME) goes into a %-style format: a "%" in it
    # would turn every log line into a formatting error.
    escaped = name.replace("%", "%%")
    logging.basicConfig(level=level.upper(), stream=sys.stderr,
                        format=f"%(asctime)s {escaped} %(levelname)s %(name)s: %(message)s")


# ZMTP heartbeats on the router-executor connection, set on both ends, and on the executor's connection to the
# control plane. A peer whose host lost power or its network, or whose process is frozen (SIGSTOP, a paused VM or
# container), closes nothing: without them its connection stayed up for good, the router kept sending it requests
# that waited out router.request_timeout_s, and an executor never redialled a router whose host had come back.
# libzmq's I/O thread answers the pings, so a busy Python thread holding the GIL does not miss them. A missed one (no
# traffic for the timeout after a ping) closes the connection, which the router handles as a crash and the executor
# as a reset (it redials).
def keep_alive(sock: zmq.Socket, timeout_s: float) -> None:
    """Ping the peers of ``sock`` every third of ``timeout_s``; close a connection silent for ``timeout_s`` after a
    ping (router.keepalive_s; 0: no heartbeats)."""
    if timeout_s > 0:
        sock.setsockopt(zmq.HEARTBEAT_IVL, max(1, round(timeout_s * 1000 / 3)))
        sock.setsockopt(zmq.HEARTBEAT_TIMEOUT, max(1, round(timeout_s * 1000)))


def ipv6_ready(sock: zmq.Socket, address: str) -> None:
    """Turn ZMQ_IPV6 on for an IPv6 literal (tcp://[::1]:5555): libzmq refuses one on a socket without it
    ("No such device"). Only there: other addresses keep the IPv4 sockets they have always had."""
    if address.startswith("tcp://["):
        sock.setsockopt(zmq.IPV6, 1)


def connect(sock: zmq.Socket, address: str) -> None:
    """``sock.connect(address)``, IPv6 literals included."""
    ipv6_ready(sock, address)
    sock.connect(address)


def bind(sock: zmq.Socket, address: str, key: str) -> None:
    """``sock.bind(address)``; a failure (the port taken by another process, an address not on this host) is
    a ConfigError naming the config key, so the service exits 2 with one line instead of a traceback."""
    try:
        ipv6_ready(sock, address)
        sock.bind(address)
    except zmq.ZMQError as exc:
        sock.close(linger=0)
        raise ConfigError(f"{key} {address}: cannot bind ({exc.strerror})") from None


def exit_on_config_error(exc: ConfigError) -> None:
    print(f"config error: {exc}", file=sys.stderr)
    raise SystemExit(2)


def load_or_exit(path: str) -> ClusterConfig:
    try:
        return load_config(path)
    except ConfigError as exc:
        exit_on_config_error(exc)


def stop_event(parent_pid: int = 0) -> threading.Event:
    """An event set by SIGINT/SIGTERM, or when the launching process disappears."""
    stop = threading.Event()

    def handler(signum, frame):
        logging.getLogger("robion").info("signal %d: shutting down", signum)
        stop.set()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)
    if parent_pid:
        watch_parent(parent_pid, stop.set, stop)
    return stop


def watch_parent(parent_pid: int, on_gone: Callable[[], None], stop: threading.Event | None = None) -> None:
    """Call ``on_gone`` once the launching process ``parent_pid`` is gone (checked every 0.5 s until ``stop``).

    A child of the launcher watches its parent pid (a reused pid cannot fool that). A process started by hand with
    the launcher's --parent-pid (an executor restarted under a running `robion up`, with the command line `ps`
    showed) is no child of it: it watches that the pid exists. It used to take "not my parent" for "gone" and quit."""
    stop = stop or threading.Event()
    child = os.getppid() == parent_pid

    def alive() -> bool:
        if child:
            return os.getppid() == parent_pid
        try:
            os.kill(parent_pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:  # exists, under another user
            return True
        return True

    def watch() -> None:
        while not stop.wait(0.5):
            if not alive():
                logging.getLogger("robion").warning("launcher %d is gone: shutting down", parent_pid)
                on_gone()
                return

    threading.Thread(target=watch, daemon=True, name="parent-watch").start()


def monitor_events(events: zmq.Socket) -> list[int]:
    """Read every event a socket monitor (``sock.get_monitor_socket(...)``) holds, oldest first."""
    out = []
    while True:
        try:
            out.append(recv_monitor_message(events, zmq.NOBLOCK)["event"])
        except zmq.Again:
            return out


def connected_again(events: zmq.Socket) -> bool:
    """Read every event a socket monitor (``sock.get_monitor_socket(zmq.EVENT_CONNECTED)``) holds; True when
    one was a (re)connect: the peer may be a restarted process that knows nothing of this one yet."""
    return zmq.EVENT_CONNECTED in monitor_events(events)


def connection_up(events: zmq.Socket, up: bool) -> bool:
    """Read every event a socket monitor (``sock.get_monitor_socket(zmq.EVENT_CONNECTED | zmq.EVENT_DISCONNECTED)``)
    holds; whether the connection is up after them (``up``: as it was before them)."""
    for event in monitor_events(events):
        if event in (zmq.EVENT_CONNECTED, zmq.EVENT_DISCONNECTED):
            up = event == zmq.EVENT_CONNECTED
    return up
