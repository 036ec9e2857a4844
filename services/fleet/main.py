"""Fleet process: simulated robots against a running router; prints the SLO report."""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys

from services.fleet.robots import check_settings, run_fleet
from shared.client import RobionError
from shared.config import dial_address, valid_address
from shared.files import unwritable, write_atomic
from shared.service import load_or_exit, log_level, setup_logging, watch_parent

log = logging.getLogger("robion.fleet")


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
    p.add_argument("--log-level", type=log_level, default="WARNING")
    p.add_argument("--parent-pid", type=int, default=0)
    args = p.parse_args(argv)
    setup_logging("fleet", args.log_level)
    if args.parent_pid:
        # Its launcher (`robion demo`) gone, its cluster goes too: a report of robots answered by nobody would
        # only mislead, and a load generator holds nothing worth a clean shutdown.
        watch_parent(args.parent_pid, lambda: os._exit(1))
    cfg = load_or_exit(args.config)
    f = cfg.fleet
    address = args.address or dial_address(cfg.router.bind)
    # An option given as 0 is a value to check, not "use the config's" (only None is).
    robots = f.robots if args.robots is None else args.robots
    hz = f.hz if args.hz is None else args.hz
    duration_s = f.duration_s if args.duration is None else args.duration
    network = args.network or f.network
    seed = f.seed if args.seed is None else args.seed
    try:
        check_settings(robots, hz, duration_s, network, seed)
    except ValueError as exc:
        p.error(f"--{exc}")  # usage and the bad option on stderr, exit code 2
    if args.json and (why := unwritable(args.json)):
        p.error(f"--json: {why}")
    if args.address and not valid_address(args.address):  # zmq would raise ZMQError "Invalid argument"
        p.error(f"--address: expected an address like tcp://HOST:PORT, got {args.address!r}")
    try:
        report = run_fleet(address, robots=robots, hz=hz, duration_s=duration_s,
                           seed=seed, network=network, models=f.models)
    except (ValueError, RobionError) as exc:
        log.error("%s", exc)
        return 1
    print(f"{report.robots} robots at {report.hz:g} Hz for {report.duration_s:g} s, network {report.network}:")
    print(report.table())
    if args.json:
        # A model without a successful reply has NaN percentiles: null in the file, since a bare NaN
        # is not JSON (jq and JSON.parse refuse the whole report).
        models = {name: {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in m.items()}
                  for name, m in report.to_dict()["models"].items()}
        text = json.dumps({**report.to_dict(), "models": models}, indent=2, allow_nan=False) + "\n"
        try:
            # Whole or not at all: opened for writing first, a failed write left the previous report truncated.
            write_atomic(args.json, text)
        except OSError as exc:
            log.error("--json: cannot write %s (%s); the report is only the table above", args.json, exc)
            return 1
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
