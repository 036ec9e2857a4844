"""Fleet process: simulated robots against a running router; prints the SLO report."""

from __future__ import annotations

import argparse
import json
import sys

from services.fleet.robots import run_fleet
from shared.config import dial_address
from shared.service import load_or_exit, setup_logging


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="robion-fleet", description=__doc__)
    p.add_argument("-c", "--config", required=True, help="cluster config (router address and fleet defaults)")
    p.add_argument("--address", help="router address; default: router.bind of the config")
    p.add_argument("--robots", type=int)
    p.add_argument("--hz", type=float)
    p.add_argument("--duration", type=float)
    p.add_argument("--seed", type=int)
    p.add_argument("--network")
    p.add_argument("--json", metavar="FILE", help="also write the report as JSON")
    p.add_argument("--log-level", default="WARNING")
    p.add_argument("--parent-pid", type=int, default=0)
    args = p.parse_args(argv)
    setup_logging("fleet", args.log_level)
    cfg = load_or_exit(args.config)
    f = cfg.fleet
    address = args.address or dial_address(cfg.router.bind)
    report = run_fleet(address, robots=args.robots or f.robots, hz=args.hz or f.hz,
                       duration_s=args.duration or f.duration_s, seed=f.seed if args.seed is None else args.seed,
                       network=args.network or f.network, models=f.models)
    print(f"{report.robots} robots at {report.hz:g} Hz for {report.duration_s:g} s, network {report.network}:")
    print(report.table())
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(report.to_dict(), fh, indent=2)
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
