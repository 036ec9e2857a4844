"""Router process: robots in, executors out, routing table from the control plane."""

from __future__ import annotations

from services.router.frontend import Router
from shared.service import load_or_exit, service_args, setup_logging, stop_event


def main(argv: list[str] | None = None) -> int:
    args = service_args("router", argv)
    setup_logging("router", args.log_level)
    cfg = load_or_exit(args.config)
    stop = stop_event(args.parent_pid)
    Router(cfg).run(stop)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
