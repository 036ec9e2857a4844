"""Prometheus metrics of each service, served on its own /metrics port.

Names follow Prometheus conventions (robion_<thing>_<unit>, _total counters, _seconds
histograms) and echo Triton's vocabulary where operators know it: inference count vs
execution count, whose ratio is the mean batch size.
"""

from __future__ import annotations

import logging
import math
from collections import deque

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, start_http_server

log = logging.getLogger("robion.metrics")

# Bounds at the paper's deadlines (SmolVLA 50, GR00T 53, XR0 117, pi0 156 ms), so a p99 read from the histogram is
# not interpolated across one.
LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.02, 0.035, 0.05, 0.053, 0.075, 0.1, 0.117, 0.125, 0.156, 0.2, 0.3,
                   0.5, 1.0, 2.5)
STAGE_BUCKETS = (0.0005, 0.001, 0.002, 0.004, 0.006, 0.008, 0.01, 0.015, 0.02, 0.03, 0.05, 0.1, 0.25)
BATCH_BUCKETS = (1, 2, 4, 8, 16, 32, 64, 128, 256)  # up to the config's largest engine.max_batch (MAX_BATCH)


def serve(registry: CollectorRegistry, port: int, addr: str = "0.0.0.0") -> bool:
    """Expose ``registry`` on http://addr:port/metrics; a port already taken or out of range is logged, not fatal."""
    if port <= 0:
        return False
    try:
        start_http_server(port, addr=addr, registry=registry)
    except (OSError, OverflowError) as exc:  # OverflowError: a port above 65535 (an executor's --metrics-port)
        log.error("cannot serve metrics on port %d: %s", port, exc)
        return False
    return True


class RouterMetrics:
    def __init__(self) -> None:
        r = self.registry = CollectorRegistry()
        self.requests = Counter("robion_router_requests_total", "Requests answered by the router, by outcome",
                                ["model", "status"], registry=r)
        self.latency = Histogram("robion_router_request_duration_seconds",
                                 "Time from forwarding a request to an executor until its reply with actions "
                                 "(errors: robion_router_requests_total)", ["model"],
                                 buckets=LATENCY_BUCKETS, registry=r)
        # What robots see (less the network): every request for a served model counts, answered by an executor or by
        # the router itself (a stalled or restarted executor, a time-out, overload, a refusal). An executor's own
        # robion_slo_* count only what reached it, timed from when it read the request.
        self.slo_met = Counter("robion_router_slo_met_total", "Requests for a served model answered with actions "
                               "within its deadline, timed at the router from receipt to answer", ["model"], registry=r)
        self.slo_missed = Counter("robion_router_slo_missed_total", "Requests for a served model answered late or "
                                  "with an error, the router's own answers included", ["model"], registry=r)
        self.in_flight = Gauge("robion_router_in_flight_requests", "Requests forwarded and not yet answered", registry=r)
        self.table_version = Gauge("robion_router_routing_table_version", "Version of the routing table in use", registry=r)
        self.executors = Gauge("robion_router_executors", "Executors the routing table routes requests to", registry=r)

    def serve_models(self, models) -> None:
        """Give each served model its SLO series at 0 (a ratio of two counters is empty while one has no series)."""
        for m in models:
            self.slo_met.labels(m)
            self.slo_missed.labels(m)


class ExecutorMetrics:
    def __init__(self, executor: str, device: str, models: dict[str, float], window: int = 1000) -> None:
        r = self.registry = CollectorRegistry()
        self.executor = executor
        self.gpu = device
        self.slo_s = models
        self.requests = Counter("robion_requests_total", "Requests answered by the executor, by outcome",
                                ["model", "status"], registry=r)
        self.latency = Histogram("robion_request_duration_seconds", "Server time from receipt to reply, of requests "
                                 "answered with actions (errors and shed requests: robion_requests_total)",
                                 ["model"], buckets=LATENCY_BUCKETS, registry=r)
        self.queue_wait = Histogram("robion_queue_wait_seconds", "Time a request waited before its batch started",
                                    ["model"], buckets=LATENCY_BUCKETS, registry=r)
        self.stage = Histogram("robion_stage_duration_seconds", "Duration of a stage as seen by its requests",
                               ["model", "stage"], buckets=STAGE_BUCKETS, registry=r)
        self.slo_met = Counter("robion_slo_met_total", "Replies sent within the model's deadline (server side)",
                               ["model"], registry=r)
        self.slo_missed = Counter("robion_slo_missed_total", "Requests answered late or with an error",
                                  ["model"], registry=r)
        self.slo_attainment = Gauge("robion_slo_attainment_ratio",
                                    f"Share of the last {window} requests answered within the deadline (server side)",
                                    ["model"], registry=r)
        self.queue_depth = Gauge("robion_queue_depth", "Requests waiting in the model's queue", ["model"], registry=r)
        self.inference_count = Counter("robion_inference_count_total", "Requests executed (batch members)",
                                       ["model"], registry=r)
        self.execution_count = Counter("robion_execution_count_total", "Batches executed; inference/execution = mean batch",
                                       ["model"], registry=r)
        self.batch_size = Histogram("robion_batch_size", "Batch size per stage execution", ["model", "stage"],
                                    buckets=BATCH_BUCKETS, registry=r)
        self.lockstep = Histogram("robion_lockstep_duration_seconds", "Duration of a lockstep", buckets=STAGE_BUCKETS,
                                  registry=r)
        self.lockstep_gap = Histogram("robion_lockstep_gap_seconds", "CPU gap between locksteps",
                                      buckets=(1e-5, 2.5e-5, 5e-5, 1e-4, 2.5e-4, 5e-4, 1e-3, 5e-3), registry=r)
        self.sm_level = Gauge("robion_vlm_sm_level", "SMs the VLM stream was restricted to in the last lockstep "
                              "(the device's SM count when unrestricted; NaN before the first, and on a CPU)",
                              registry=r)
        # An unlabelled gauge exports 0 from the start, which a dashboard reads as a VLM restricted to no SMs.
        self.sm_level.set(math.nan)
        # Which executor (and device) this endpoint is: Prometheus's info idiom. Not robion_executor_up: that is the
        # control plane's, which reads 0 for a configured executor that is down; a copy here, always 1 while
        # scrapeable, doubled every executor on a dashboard of it.
        self.info = Gauge("robion_executor_info", "Always 1; names the executor and device of this endpoint",
                          ["executor", "device"], registry=r)
        self.gpu_memory = Gauge("robion_gpu_memory_used_bytes", "Device memory used by this executor", ["gpu"], registry=r)
        self.window = window
        self._recent: dict[str, deque[bool]] = {}
        self.info.labels(executor, device).set(1)
        self.serve_models(models)

    def serve_models(self, models: dict[str, float]) -> None:
        """The models served now (name -> deadline in seconds), at start and after each reload. The series exist
        from the start, so dashboards show zeros, not gaps (a ratio of two counters is empty while one has none).
        A model added, or served at another deadline, starts a fresh attainment window: the one it had before
        describes other settings (or another time). Series of models no longer served are removed."""
        for m in set(self._recent) - set(models):
            del self._recent[m]
            for metric in (self.slo_attainment, self.queue_depth):
                try:
                    metric.remove(m)
                except KeyError:
                    pass
        for m, slo_s in models.items():
            if m not in self._recent or self.slo_s.get(m) != slo_s:
                self._recent[m] = deque(maxlen=self.window)
                self.slo_attainment.labels(m).set(1.0)
            self.queue_depth.labels(m)
            self.slo_met.labels(m)
            self.slo_missed.labels(m)
        self.slo_s = dict(models)

    def observe_result(self, model: str, status: str, server_s: float, queue_s: float, vlm_s: float,
                       action_s: float) -> None:
        self.requests.labels(model, status).inc()
        met = status == "ok" and server_s <= self.slo_s.get(model, float("inf"))
        (self.slo_met if met else self.slo_missed).labels(model).inc()
        recent = self._recent.get(model)
        if recent is not None:  # a model a reload took away keeps its counters but gets no gauge series back
            recent.append(met)
            self.slo_attainment.labels(model).set(sum(recent) / len(recent))
        if status == "ok":
            self.latency.labels(model).observe(server_s)
            self.queue_wait.labels(model).observe(queue_s)
            self.stage.labels(model, "vlm").observe(vlm_s)
            self.stage.labels(model, "action").observe(action_s)

    def observe_batch(self, model: str, size: int) -> None:
        self.inference_count.labels(model).inc(size)
        self.execution_count.labels(model).inc()
        self.batch_size.labels(model, "vlm").observe(size)
        self.batch_size.labels(model, "action").observe(size)


class ControlMetrics:
    def __init__(self) -> None:
        r = self.registry = CollectorRegistry()
        self.executors = Gauge("robion_executors_registered", "Executors registered and heartbeating", registry=r)
        self.executor_up = Gauge("robion_executor_up", "1 while the executor heartbeats", ["executor"], registry=r)
        self.table_version = Gauge("robion_routing_table_version", "Current routing table version", registry=r)
        self.robots_assigned = Gauge("robion_robots_assigned", "Robots of a model assigned to a GPU (executor)",
                                     ["model", "gpu"], registry=r)
