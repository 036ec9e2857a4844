"""Router process: robots in, executors out, routing table from the control plane."""

from __future__ import annotations

from shared.config import ConfigError
from shared.service import exit_on_config_error, load_or_exit, service_args, setup_logging, stop_event


def main(argv: list[str] | None = None) -> int:
    args = service_args("router", argv)
    setup_logging("router", args.log_level)
    # The signal handlers go in before any slow start-up work: loading the config imports torch (about
    # a second), and until the handlers are installed a launcher's SIGTERM (`robion up` stopping, docker
    # stop) kills the process with the signal instead of the clean exit 0 a stop is. For the same reason
    # the router's own modules (numpy, prometheus) are imported only now (zmq already is, by shared.service,
    # in about 25 ms).
    stop = stop_event(args.parent_pid)
    import zmq

    from services.router.frontend import Router

    cfg = load_or_exit(args.config)
    context = zmq.Context()
    try:
        router = Router(cfg, context)
    except ConfigError as exc:  # a port another process holds
        context.destroy(linger=0)
        exit_on_config_error(exc)
    # A signal that came during start-up leaves `stop` set: run() returns at once, closing cleanly.
    router.run(stop)
    # Waits for the answers the router sent while closing (bounded by its sockets' linger); exiting
    # without it could drop them.
    context.term()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
