"""Simulated robots over real sockets: each sends a request every 1/f s on its own clock."""

from __future__ import annotations

import logging
import time
from collections import Counter
from dataclasses import asdict, dataclass, field

import numpy as np
import zmq

from shared.client import Completion, RequestTimeout, RobionError, RobotClient, wait_any
from shared.config import FLEET_MAX_HZ, FLEET_MAX_ROBOTS, positive_number
from shared.netmodel import NETWORKS

log = logging.getLogger("robion.fleet")

INSTRUCTIONS = ["pick up the red block", "open the drawer", "put the bowl on the plate", "stack the cups"]
LATE_SEND_WARN_MS = 5.0  # a send this late is worth a note under the report


@dataclass
class ModelReport:
    model: str
    robots: int
    sent: int = 0
    replies: int = 0
    errors: dict[str, int] = field(default_factory=dict)
    slo_ms: float = 0.0
    slo_attainment: float = 0.0  # share of sent requests answered within the deadline, end to end
    p50_ms: float = 0.0
    p99_ms: float = 0.0
    server_p50_ms: float = 0.0
    # How late this process sent its robots' requests (a host too slow for the fleet it drives). Latencies count
    # from the scheduled send, so the lag is in them, as a robot whose request left late would see it.
    send_lag_p99_ms: float = 0.0
    send_lag_max_ms: float = 0.0


@dataclass
class FleetReport:
    network: str
    robots: int
    hz: float
    duration_s: float
    models: dict[str, ModelReport]

    def to_dict(self) -> dict:
        return asdict(self)

    def table(self) -> str:
        rows = [f"{'model':<16}{'robots':>7}{'sent':>7}{'ok':>7}{'errors':>8}{'SLO ms':>8}{'SLO-AT':>9}{'p50 ms':>9}"
                f"{'p99 ms':>9}"]
        for r in self.models.values():
            rows.append(f"{r.model:<16}{r.robots:>7}{r.sent:>7}{r.replies:>7}{sum(r.errors.values()):>8}{r.slo_ms:>8g}"
                        f"{100 * r.slo_attainment:>8.1f}%{r.p50_ms:>9.1f}{r.p99_ms:>9.1f}")
        late = max((r.send_lag_max_ms for r in self.models.values()), default=0.0)
        if late > LATE_SEND_WARN_MS:
            rows.append(f"note: this host sent requests up to {late:.0f} ms after their time (p99 "
                        f"{max(r.send_lag_p99_ms for r in self.models.values()):.1f} ms); latencies count from the "
                        "scheduled send, so the lag is in them: drive fewer robots per fleet process")
        return "\n".join(rows)


def check_settings(robots: int, hz: float, duration_s: float, network: str, seed: int = 0) -> None:
    """ValueError naming the first setting a fleet cannot run with (a rate <= 0 would never advance a robot's clock)."""
    if isinstance(robots, bool) or not isinstance(robots, int) or not 1 <= robots <= FLEET_MAX_ROBOTS:
        raise ValueError(f"robots: expected a positive integer up to {FLEET_MAX_ROBOTS}, got {robots!r}")
    for name, value in (("hz", hz), ("duration", duration_s)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not positive_number(value):
            raise ValueError(f"{name}: expected a positive number, got {value!r}")
    if hz > FLEET_MAX_HZ:
        # A period below the monotonic clock's resolution never advanced a robot's next send: a hang.
        raise ValueError(f"hz: expected at most {FLEET_MAX_HZ:g} requests per second per robot, got {hz!r}")
    if duration_s < 1 / hz:
        # Shorter, and a robot whose random start falls after the window sends nothing: a report of 0 sent.
        raise ValueError(f"duration: expected at least one period (1 / hz = {1 / hz:g} s), got {duration_s!r}")
    if network not in NETWORKS:
        raise ValueError(f"network: expected one of {', '.join(sorted(NETWORKS))}, got {network!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:  # numpy's default_rng refuses it later
        raise ValueError(f"seed: expected a non-negative integer, got {seed!r}")


# How long the robots of a fleet may take to connect before its clock starts. A clock started while thousands of
# connections were still being accepted (a listen backlog overflowing retries a SYN after 1 s) counted the fleet's own
# start-up as lag and UNAVAILABLE answers.
CONNECT_TIMEOUT_S = 10.0


def _connect_all(clients: list[RobotClient], timeout_s: float) -> int:
    """Wait until every client's connection to the router is up (its socket takes a send: the clients queue only to
    a connected router); returns how many were still not connected after ``timeout_s``."""
    waiting = {c.socket for c in clients}
    end = time.monotonic() + timeout_s
    while waiting and time.monotonic() < end:
        poller = zmq.Poller()
        for sock in waiting:
            poller.register(sock, zmq.POLLOUT)
        for sock, _ in poller.poll(timeout=100):
            waiting.discard(sock)
    return len(waiting)


def run_fleet(address: str, robots: int, hz: float, duration_s: float, seed: int = 0, network: str = "wifi7",
              models: list[str] | None = None, drain_s: float = 5.0) -> FleetReport:
    """Drive ``robots`` simulated robots at ``hz`` for ``duration_s``; robots are spread over ``models`` round-robin.

    Raises ValueError for settings out of range and for a router that serves none of the models.
    """
    check_settings(robots, hz, duration_s, network, seed)
    rng = np.random.default_rng(seed)
    net = NETWORKS[network]
    # A context of its own, sized for the fleet: the shared one allows 1023 sockets, and more robots ended in a
    # ZMQError traceback.
    ctx = zmq.Context()
    ctx.set(zmq.MAX_SOCKETS, robots + 16)
    clients: list[RobotClient] = []
    try:
        with RobotClient(address, robot_id=f"fleet-probe-{seed}", context=ctx) as probe:
            meta = probe.metadata()
        if not meta:
            # No executor has described a model yet (the cluster is still starting, or none was placed).
            raise ValueError(f"the router at {address} serves no models yet")
        models = models or sorted(meta)
        missing = [m for m in models if m not in meta]
        if missing:
            raise ValueError(f"models not served: {missing}")
        # Robots are spread round-robin, so with fewer robots than models the last models get none. They are left out
        # of the report, where they would read 0% SLO attainment for requests never sent.
        models = models[:robots]

        # Requests in flight at the end are waited for as long as the longest deadline, and a client gives up on a
        # request no sooner: a fixed 5 s (10 s) counted answers still in time as unanswered (timed out).
        longest_s = max(meta[m].deadline_ms for m in models) / 1e3
        drain_s = max(drain_s, longest_s)
        obs = []
        for i in range(robots):
            model = models[i % len(models)]
            info = meta[model]
            try:
                clients.append(RobotClient(address, robot_id=f"robot-{seed}-{i:03d}", context=ctx,
                                           timeout_s=max(10.0, longest_s + 1.0)))
            except zmq.ZMQError as exc:
                raise ValueError(f"robots: could not open a connection for robot {i + 1} of {robots} ({exc}): drive "
                                 "fewer robots per fleet process, or raise the open-files limit (ulimit -n)") from None
            images = {cam: rng.integers(0, 256, info.image_shape, dtype=np.uint8) for cam in info.cameras}
            state = rng.standard_normal(info.state_dim).astype(np.float32)
            obs.append((model, images, state, INSTRUCTIONS[i % len(INSTRUCTIONS)]))

        not_connected = _connect_all(clients, CONNECT_TIMEOUT_S)
        if not_connected:
            raise ValueError(f"robots: {not_connected} of {robots} robots could not connect to the router at {address} "
                             f"within {CONNECT_TIMEOUT_S:g} s")
        period = 1.0 / hz
        start = time.monotonic() + 0.05
        next_send = [start + rng.uniform(0, period) for _ in range(robots)]
        end = start + duration_s
        sent: dict[str, list[str]] = {m: [] for m in models}
        scheduled: dict[str, float] = {}  # request id -> when its robot was to send it
        lag: dict[str, list[float]] = {m: [] for m in models}
        done: dict[str, Completion] = {}
        while True:
            now = time.monotonic()
            for i, c in enumerate(clients):
                while next_send[i] <= now and next_send[i] < end:
                    model, images, state, text = obs[i]
                    try:
                        rid = c.submit(model, images, state, text)
                    except RobionError as exc:
                        # Not sent (send queue full with the router unreachable, a request the router would
                        # refuse): that request failed, not the run. It counts as sent with its error.
                        rid = f"unsent-{i}-{next_send[i]}"
                        done[rid] = Completion(request_id=rid, model=model, sent_at=now, received_at=now, error=exc)
                    sent[model].append(rid)
                    scheduled[rid] = next_send[i]
                    lag[model].append(time.monotonic() - next_send[i])
                    next_send[i] += period  # on the robot's clock, whether or not a reply came
            upcoming = min((t for t in next_send if t < end), default=None)
            if upcoming is None:
                if all(c.pending() == 0 for c in clients) or now > end + drain_s:
                    break
                wait = 0.05
            else:
                wait = max(0.0, upcoming - time.monotonic())
            for _, comp in wait_any(clients, wait):
                done[comp.request_id] = comp
    finally:
        for c in clients:
            c.close()
        # destroy, not term: a socket left open (a Ctrl-C inside a client's construction) held term() for good.
        ctx.destroy(linger=0)

    reports = {}
    for model in models:
        info = meta[model]
        ids = sent[model]
        comps = [done[i] for i in ids if i in done]
        ok = [c for c in comps if c.ok]
        e2e = np.array([(c.received_at - scheduled[c.request_id] + net.latency_s(c.request_bytes, c.reply_bytes)) * 1e3
                        for c in ok])
        late = np.array(lag[model]) * 1e3
        server = np.array([c.timings.server_ms for c in ok])
        met = int((e2e <= info.deadline_ms).sum()) if len(e2e) else 0
        # A reply the SDK gave up on (RequestTimeout, code UNAVAILABLE) is as lost as one still awaited when
        # the drain ends: both are NO_REPLY, never mixed with the server's own UNAVAILABLE answers.
        errors = Counter(c.error.code.value for c in comps
                         if c.error is not None and not isinstance(c.error, RequestTimeout))
        unanswered = len(ids) - len(comps) + sum(isinstance(c.error, RequestTimeout) for c in comps)
        if unanswered:
            errors["NO_REPLY"] = unanswered
        reports[model] = ModelReport(
            model=model, robots=sum(1 for o in obs if o[0] == model), sent=len(ids), replies=len(ok),
            errors=dict(errors), slo_ms=info.deadline_ms, slo_attainment=met / len(ids) if ids else 0.0,
            p50_ms=float(np.percentile(e2e, 50)) if len(e2e) else float("nan"),
            p99_ms=float(np.percentile(e2e, 99)) if len(e2e) else float("nan"),
            server_p50_ms=float(np.percentile(server, 50)) if len(server) else float("nan"),
            send_lag_p99_ms=float(np.percentile(late, 99)) if len(late) else 0.0,
            send_lag_max_ms=float(late.max()) if len(late) else 0.0)
    return FleetReport(network=network, robots=robots, hz=hz, duration_s=duration_s, models=reports)
