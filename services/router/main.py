"""Router process: robots in, executors out, routing table from the control plane."""

from __future__ import annotations

import zmq

from services.router.frontend import Router
from shared.service import load_or_exit, service_args, setup_logging, stop_event


def main(argv: list[str] | None = None) -> int:
    args = service_args("router", argv)
    setup_logging("router", args.log_level)
    cfg = load_or_exit(args.config)
    stop = stop_event(args.parent_pid)
    context = zmq.Context()
    Router(cfg, context).run(stop)
    # Waits for the answers the router sent while closing (bounded by its sockets' linger); exiting
    # without it could drop them.
    context.term()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
