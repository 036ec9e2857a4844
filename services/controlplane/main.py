"""Control-plane process: desired state from the config, executor registry, routing tables."""

from __future__ import annotations

from services.controlplane.server import ControlPlane
from shared.config import ConfigError
from shared.service import exit_on_config_error, load_or_exit, service_args, setup_logging, stop_event


def main(argv: list[str] | None = None) -> int:
    args = service_args("control", argv)
    setup_logging("control", args.log_level)
    stop = stop_event(args.parent_pid)  # before the config load: a SIGTERM from then on is a clean stop
    cfg = load_or_exit(args.config)
    try:
        plane = ControlPlane(cfg)
    except ConfigError as exc:  # its port held by another process
        exit_on_config_error(exc)
    plane.run(stop)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
