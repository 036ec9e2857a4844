"""Executor process: the models placed on one device, their queues and the engine running them."""

from __future__ import annotations

import logging
import os
import threading

import torch

from services.executor.engine import ServedModel, make_engine
from services.executor.tokens import tokenizer_for
from services.executor.transport import ExecutorIO, ServedInput
from shared.config import ExecutorConfig
from shared.metrics import ExecutorMetrics, serve
from shared.models import build_model
from shared.protocol import ModelInfo
from shared.service import load_or_exit, service_args, setup_logging, stop_event

log = logging.getLogger("robion.executor")


def _args(p) -> None:
    p.add_argument("--name", default=os.environ.get("HOSTNAME", ""),
                   help="executor name: one from the config, or a new one (then --models is needed); default $HOSTNAME")
    p.add_argument("--models", help="comma-separated models for an executor not in the config (scaled-out replicas)")
    p.add_argument("--device", help="override the device, e.g. cuda:1")
    p.add_argument("--metrics-port", type=int, help="override the /metrics port (0 disables)")


def main(argv: list[str] | None = None) -> int:
    args = service_args("executor", argv, _args)
    setup_logging(f"executor[{args.name}]", args.log_level)
    cfg = load_or_exit(args.config)
    try:
        ex_cfg = cfg.executor(args.name)
    except KeyError:
        if not args.models or not args.name:
            log.error("no executor named %r in %s; give --name and --models for a replica outside the config",
                      args.name, args.config)
            return 2
        ex_cfg = ExecutorConfig(name=args.name, models=args.models.split(","))
        unknown = [m for m in ex_cfg.models if m not in {mc.name for mc in cfg.models}]
        if unknown:
            log.error("--models: no models named %s in %s", unknown, args.config)
            return 2
    if args.device:
        ex_cfg.device = args.device
    device = torch.device(ex_cfg.device)
    stop = stop_event(args.parent_pid)

    models: dict[str, ServedModel] = {}
    served: dict[str, ServedInput] = {}
    for name in ex_cfg.models:
        mc = cfg.model(name)
        model = build_model(mc.arch, mc.size, seed=mc.seed, device=device)
        io = model.io
        models[name] = ServedModel(name, model, mc.slo_ms / 1e3)
        info = ModelInfo(cameras=list(io.cameras), image_shape=list(io.image_shape), state_dim=io.state_dim,
                         horizon=io.horizon, action_dim=io.action_dim, deadline_ms=mc.slo_ms, arch=mc.arch)
        served[name] = ServedInput(io=io, slo_s=mc.slo_ms / 1e3, tokenize=tokenizer_for(mc, io.prompt_len), info=info)
        log.info("loaded %s (%s/%s, seed %d) on %s", name, mc.arch, mc.size, mc.seed, device)

    transport: ExecutorIO | None = None

    def on_results(results):
        transport.on_results(results)

    engine = make_engine(models, cfg.engine, device, on_results)
    metrics = ExecutorMetrics(args.name, ex_cfg.device, {n: s.slo_s for n, s in served.items()})
    index = next((i for i, e in enumerate(cfg.executors) if e.name == args.name), 0)
    serve(metrics.registry, args.metrics_port if args.metrics_port is not None else ex_cfg.metrics_port_or_default(index))
    transport = ExecutorIO(args.name, cfg, ex_cfg.device, served, engine, metrics)
    engine.prepare()
    engine_stop = threading.Event()
    engine_thread = threading.Thread(target=engine.run, args=(engine_stop,), name="engine", daemon=True)
    engine_thread.start()
    log.info("serving %s with the %s engine", sorted(models), cfg.engine.kind)
    try:
        transport.run(stop)
    finally:
        engine_stop.set()
        engine_thread.join(timeout=30)
        transport.drain()
        transport.close()
    log.info("stopped: %s", transport.stats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
