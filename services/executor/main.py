"""Executor process: the models placed on one device, their queues and the engine running them."""

from __future__ import annotations

import logging
import os

import torch

from services.executor.engine import resolve_kind
from services.executor.hosting import EngineSlot, ModelStore
from services.executor.limits import measure_limits
from services.executor.transport import ExecutorIO
from shared.config import ClusterConfig, ExecutorConfig, executor_name_problem, parse_devices, valid_device
from shared.metrics import ExecutorMetrics, serve
from shared.models.base import is_device_fault
from shared.placement import memory_shortfall
from shared.service import load_or_exit, service_args, setup_logging, stop_event

log = logging.getLogger("robion.executor")


def _args(p) -> None:
    p.add_argument("--name", default=os.environ.get("HOSTNAME", ""),
                   help="executor name: one from the config, or a new one (then --models is needed); default $HOSTNAME")
    p.add_argument("--models", help="comma-separated models for an executor not in the config (scaled-out replicas)")
    p.add_argument("--device", help="override the device, e.g. cuda:1")
    p.add_argument("--metrics-port", type=int, help="override the /metrics port (0 disables)")


def _missing_gpus(cfg: ClusterConfig, device: torch.device) -> str:
    """Why the GPUs this executor would use are not there ("" when they are): torch fails on a GPU index past
    the host's, or on any GPU without a driver, with a traceback deep in its first CUDA call."""
    wanted = [(f"device {device}", device)]
    if cfg.engine.kind == "interdisagg":
        for key in ("vlm_devices", "action_devices"):
            wanted += [(f"engine.{key} {d}", torch.device(d)) for d in parse_devices(getattr(cfg.engine, key))]
    if all(dev.type != "cuda" for _, dev in wanted):
        return ""  # a CPU executor does not ask the driver anything
    count = torch.cuda.device_count()  # 0 without a CUDA build, a driver or a visible GPU
    for what, dev in wanted:
        if dev.type == "cuda" and (dev.index or 0) >= count:
            seen = (f"this host shows {count} CUDA GPU(s), cuda:0 to cuda:{count - 1}" if count
                    else "no CUDA GPU is visible here (no driver, none in CUDA_VISIBLE_DEVICES, or a CPU build of torch)")
            return f"{what}: {seen}"
    return ""


def main(argv: list[str] | None = None) -> int:
    args = service_args("executor", argv, _args)
    setup_logging(f"executor[{args.name}]", args.log_level)
    # Before any slow start-up work (config, models, graphs): a SIGTERM from then on is a clean stop.
    stop = stop_event(args.parent_pid)
    cfg = load_or_exit(args.config)
    try:
        ex_cfg = cfg.executor(args.name)
    except KeyError:
        if not args.models or not args.name:
            log.error("no executor named %r in %s; give --name and --models for a replica outside the config",
                      args.name, args.config)
            return 2
        why = executor_name_problem(args.name)
        if why:  # a configured executor's name is checked at load; a replica's only here
            log.error("--name: %s", why)
            return 2
        ex_cfg = ExecutorConfig(name=args.name, models=args.models.split(","))
        unknown = [m for m in ex_cfg.models if m not in {mc.name for mc in cfg.models}]
        if unknown:
            log.error("--models: no models named %s in %s", unknown, args.config)
            return 2
    if args.device:
        # The config's rule for `device`: torch.device would end the process with a traceback.
        if not valid_device(args.device):
            log.error("--device: expected 'cpu' or 'cuda:N', got %r", args.device)
            return 2
        ex_cfg.device = args.device
    device = torch.device(ex_cfg.device)
    missing = _missing_gpus(cfg, device)
    if missing:
        log.error("%s", missing)
        return 2
    if device.type == "cpu":
        # Several executors usually share the host's cores; intra-op threads on small CPU models
        # only contend with each other (ROBION_CPU_THREADS overrides).
        threads = os.environ.get("ROBION_CPU_THREADS", "1")
        # int() would end the process with a ValueError traceback, torch with a RuntimeError for 0
        # or a count past a C int.
        try:
            if not threads.strip().isdecimal() or int(threads) < 1:
                raise ValueError(threads)
            torch.set_num_threads(int(threads))
        except (ValueError, RuntimeError, OverflowError):
            log.error("ROBION_CPU_THREADS: expected a positive integer, got %r", threads)
            return 2

    index = next((i for i, e in enumerate(cfg.executors) if e.name == args.name), None)  # None: a replica
    if device.type == "cuda":
        # The device's free memory, not the config's memory_gb: other processes may hold some of it. A replica
        # (--models, e.g. scaled out by docker-compose) is checked as well as a configured executor.
        free, _ = torch.cuda.mem_get_info(device)
        short = memory_shortfall(cfg, args.name, ex_cfg.models, free)
        if short is not None:
            log.error("%s: %s", "--models" if index is None else f"executors[{index}].models", short)
            return 2
    store = ModelStore(device, cfg.engine.max_batch)
    try:
        hosted = store.load([cfg.model(name) for name in ex_cfg.models])
    except (OSError, ValueError, ImportError) as exc:  # weights or tokenizer files that do not fit
        log.error("cannot load models: %s", exc)
        return 2
    if stop.is_set():  # stopped while loading: measuring limits and starting the engine take seconds more
        log.info("stopped during start-up")
        return 0

    transport: ExecutorIO | None = None

    def on_results(results):
        transport.on_results(results)

    limits: dict[str, int] = {}
    if cfg.control.limits.auto:
        limits = measure_limits(cfg, args.name, hosted.models, device, stop=stop)
        if stop.is_set():  # the capacity search takes minutes: a stop ends it between epochs
            log.info("stopped during start-up")
            return 0
    slot = EngineSlot(cfg.engine, device, on_results)
    metrics = ExecutorMetrics(args.name, ex_cfg.device, {n: s.slo_s for n, s in hosted.inputs.items()})
    serve(metrics.registry, args.metrics_port if args.metrics_port is not None
          else ex_cfg.metrics_port_or_default(index or 0))
    transport = ExecutorIO(args.name, cfg, ex_cfg.device, store, slot, hosted, metrics, limits=limits)
    # The engine starts on its own thread while this one answers what the router sends meanwhile.
    try:
        took = slot.start_while(hosted, lambda started: transport.answer_while_starting(started, stop))
    except Exception as exc:
        if is_device_fault(exc):  # out of device memory (maybe held by a process that just crashed): exit 1, restart
            raise
        # Exit 2, not a traceback and 1: 1 asks a supervisor to start it again (`robion up` leaves a 2 down), and a
        # model that cannot be captured or profiled would fail the same way each time. The traceback is for the
        # model's author.
        log.error("cannot start the %s engine for %s: %s: %s (--log-level debug shows where)",
                  resolve_kind(cfg.engine.kind, device), sorted(hosted.models), type(exc).__name__, exc)
        log.debug("engine start-up failed", exc_info=True)
        slot.stop()
        transport.close()
        return 2
    served = sorted(hosted.models)
    # The slot and the transport hold what is served from now on; this frame lives until the process ends, and its
    # reference kept the first models' weights (device memory) alive after a reload dropped them.
    del hosted
    try:
        if stop.is_set():
            # Stopped while the engine started: it never registered, so the control plane never routed
            # anything here; registering now only to withdraw at once would make it plan twice for nothing.
            log.info("stopped during start-up")
        else:
            log.info("serving %s with the %s engine (ready in %.1f s)", served,
                     resolve_kind(cfg.engine.kind, device), took)
            transport.run(stop)
            # Out of routing first, engine second: stopping the engine while the router still
            # routes here would fail requests a healthy replica could serve.
            transport.withdraw()
    finally:
        slot.stop()
        transport.drain()
        transport.close()
    if transport.fatal.is_set():
        log.error("stopped: %s (%s)", transport.fatal_reason, transport.stats)
        return 1  # a supervisor (docker-compose's restart policy) starts it again
    log.info("stopped: %s", transport.stats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
