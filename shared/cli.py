"""The `robion` command."""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

from shared.config import ConfigError, dial_address, parse_yaml, positive_number, solve_time_limit
from shared.files import unwritable
from shared.service import load_or_exit, log_level

if TYPE_CHECKING:
    from shared.cluster import LocalCluster, RestartPolicy


def checkout_path(relative: str) -> Path:
    """A file of the source tree (configs/, bench/): beside the package in a checkout or an editable install,
    else under the working directory (an installed package, e.g. the image's /app, which has configs/ there)."""
    beside = Path(__file__).resolve().parent.parent / relative
    return beside if beside.exists() or not (Path.cwd() / relative).exists() else Path.cwd() / relative


DEFAULT_DEMO = checkout_path("configs/demo.yaml")
# How long `robion ctl` waits for an answer beyond the traffic re-solve that drain, resume and apply run first.
ANSWER_MARGIN_S = 10.0


def non_negative_int(text: str) -> int:
    """argparse type of a count: refused with a message and exit code 2, not a traceback."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}")
    return value


def positive_seconds(text: str) -> float:
    """argparse type of a --timeout: a wait of zero, a negative one (which zmq takes as "forever")
    or a non-finite one is refused by argparse with a message and exit code 2, not a traceback."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {text!r}") from None
    if not positive_number(value):
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {text!r}")
    return value


def _wait_for_signal_or_exit(cluster: "LocalCluster", restarts: "RestartPolicy") -> bool:
    """Until SIGINT or SIGTERM (then True if no service failed meanwhile), or until the router or the control plane
    has exited for good (then False): an `up` that went on waiting with its router dead reported nothing, and exited
    0 at the operator's stop. A service that fails is started again as ``restarts`` says; an executor left down is
    reported and the others keep serving (routing drops it)."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    failed = False
    down: set[str] = set()  # exited for good
    due: dict[str, float] = {}  # name -> when it is started again
    while not stop.wait(0.5):
        now = time.monotonic()
        for name in sorted(n for n, up in cluster.alive().items() if not up and n not in down and n not in due):
            code = cluster.procs[name].returncode
            failed = failed or code != 0
            delay, why = restarts.after_exit(name, code, now)
            print(f"robion up: {name} exited with code {code}: {why}", file=sys.stderr, flush=True)
            if delay is None:
                down.add(name)
            else:
                due[name] = now + delay
        if down & {"router", "control"}:
            print("robion up: stopping the cluster", file=sys.stderr, flush=True)
            return False
        for name in [n for n, at in due.items() if at <= now]:
            del due[name]
            cluster.respawn(name)
            print(f"robion up: {name} started again", file=sys.stderr, flush=True)
    return not failed


def _ignore_stops() -> None:
    """While the cluster is being stopped in order: a second Ctrl-C or SIGTERM raised KeyboardInterrupt out of
    the stop, with a traceback, and left the router and control plane to their parent watch, in no order."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)


def _say(line: str) -> None:
    print(f"  {line}", flush=True)


def cmd_up(args: argparse.Namespace) -> int:
    from shared.cluster import LocalCluster, RestartPolicy, metrics_ports_taken

    cfg = load_or_exit(args.config)
    for line in metrics_ports_taken(cfg):
        print(f"robion up: warning: {line}: that service will serve no metrics, and a scrape of the port reads "
              "whatever holds it; give it another metrics_port", file=sys.stderr, flush=True)
    cluster = LocalCluster(cfg, args.config, log_level=args.log_level)
    # Ctrl-C during start-up must still stop what was started.
    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt))
    rc = 0
    print(f"starting the cluster from {args.config} ...", flush=True)
    try:
        t0 = time.monotonic()
        status = cluster.start(timeout_s=args.timeout, progress=_say)
        print(f"robion is up in {time.monotonic() - t0:.1f} s: robots connect to {dial_address(cfg.router.bind)}; "
              f"models {sorted(status['table']['models'])} on executors {sorted(status['executors'])}. Ctrl-C stops it.",
              flush=True)
        if not _wait_for_signal_or_exit(cluster, RestartPolicy(max_restarts=args.max_restarts)):
            rc = 1
    except KeyboardInterrupt:
        pass
    except (RuntimeError, TimeoutError) as exc:  # LocalCluster.start: a service exited, or not ready in time
        print(f"robion up: {exc}", file=sys.stderr, flush=True)
        rc = 1
    finally:
        _ignore_stops()
        codes = cluster.stop()
        print(f"robion stopped: {codes}", flush=True)
    return rc


def cmd_demo(args: argparse.Namespace) -> int:
    from shared.cluster import LocalCluster

    from services.fleet.robots import check_settings

    cfg = load_or_exit(args.config)
    if args.json and (why := unwritable(args.json)):  # before the cluster starts, not after the whole run
        print(f"robion demo: --json: {why}", file=sys.stderr)
        return 2
    f = cfg.fleet
    try:  # the fleet would refuse them too, but only once the cluster had started
        check_settings(f.robots, f.hz, f.duration_s, f.network, f.seed)
    except ValueError as exc:
        key, _, why = str(exc).partition(":")  # check_settings names the fleet CLI's --duration, the config duration_s
        print(f"robion demo: fleet.{'duration_s' if key == 'duration' else key}:{why}", file=sys.stderr)
        return 2
    cluster = LocalCluster(cfg, args.config, log_level=args.log_level)
    # A stop (Ctrl-C, SIGTERM) at any point stops the fleet and the cluster, as `robion up` does.
    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt))
    print(f"starting the cluster from {args.config} ...", flush=True)
    t0 = time.monotonic()
    fleet: subprocess.Popen | None = None
    try:
        cluster.start(timeout_s=args.timeout, progress=_say)
        print(f"cluster ready in {time.monotonic() - t0:.1f} s; driving {cfg.fleet.robots} simulated robots at "
              f"{cfg.fleet.hz:g} Hz for {cfg.fleet.duration_s:g} s ...", flush=True)
        cmd = [sys.executable, "-m", "services.fleet.main", "--config", args.config, "--parent-pid", str(os.getpid())]
        if args.json:
            cmd += ["--json", args.json]
        fleet = subprocess.Popen(cmd, start_new_session=True)  # a terminal's Ctrl-C reaches us only; we stop it
        rc = fleet.wait()
    except KeyboardInterrupt:
        print("robion demo: stopped", file=sys.stderr, flush=True)
        rc = 130
    except (RuntimeError, TimeoutError) as exc:  # LocalCluster.start: a service exited, or not ready in time
        print(f"robion demo: {exc}", file=sys.stderr, flush=True)
        rc = 1
    finally:
        _ignore_stops()
        if fleet is not None and fleet.poll() is None:
            fleet.terminate()  # its report would describe a cluster being stopped under it
            try:
                fleet.wait(5)
            except subprocess.TimeoutExpired:
                fleet.kill()
        cluster.stop()
    return rc


def cmd_models(args: argparse.Namespace) -> int:
    from shared.models.cli import main as models_main

    return models_main(["--json"] * args.json + ["--size", args.size])


def cmd_plan(args: argparse.Namespace) -> int:
    from services.controlplane.planning import main as plan_main

    return plan_main(args.rest)  # its own parser: `robion plan --help` is its help


BENCHMARKS = {"capacity": "capacity.py", "router-hop": "router_hop.py", "router-flood": "router_flood.py",
              "solver": "solver_speed.py", "models": "model_latency.py", "engine-gap": "engine_gap.py",
              "colocation": "colocation.py", "traffic": "traffic.py", "interdisagg": "interdisagg.py"}


def cmd_bench(args: argparse.Namespace) -> int:
    import runpy

    if args.name is None:  # `robion bench`, `robion bench --help`: which benchmarks there are
        asked = any(a in ("-h", "--help") for a in args.rest)
        out = sys.stdout if asked else sys.stderr
        print("usage: robion bench NAME [ARGS ...]; `robion bench NAME --help` for a benchmark's own options\n"
              "benchmarks (scripts in bench/):", file=out)
        for name, file in sorted(BENCHMARKS.items()):
            print(f"  {name:<12} bench/{file}", file=out)
        return 0 if asked else 2
    script = checkout_path(f"bench/{BENCHMARKS[args.name]}")
    if not script.exists():
        print(f"benchmark script {script} is missing (run from a source checkout)", file=sys.stderr)
        return 2
    sys.argv = [str(script), *args.rest]
    try:
        runpy.run_path(str(script), run_name="__main__")
    except SystemExit as exc:
        if isinstance(exc.code, str):  # a benchmark's own refusal (SystemExit("...")): the operator must see it
            print(exc.code, file=sys.stderr)
            return 1
        return int(exc.code or 0)
    return 0


def applied_solve_limit(text: str) -> float:
    """The traffic solve's time limit a file sent with `apply` sets (0 when it sets none or is refused anyway)."""
    try:
        control = parse_yaml(text).get("control")
    except (ConfigError, AttributeError):
        return 0.0
    limit = control.get("solve_time_limit_s") if isinstance(control, dict) else None
    return float(limit) if solve_time_limit(limit) else 0.0  # the plane refuses any other value


def cmd_ctl(args: argparse.Namespace) -> int:
    from shared.protocol import ProtocolError

    try:
        return _ctl(args)
    except ProtocolError as exc:  # an answer this client cannot read (too large, malformed)
        print(f"robion ctl {args.action}: unreadable answer from the control plane: {exc.message}", file=sys.stderr)
        return 1


def _ctl(args: argparse.Namespace) -> int:
    from shared.cluster import control_request, control_status

    cfg = load_or_exit(args.config)
    address = dial_address(cfg.control.bind, cfg.control.connect)
    if args.action != "status" and not args.target:
        print(f"robion ctl {args.action}: needs {'a config file' if args.action == 'apply' else 'an executor name'}",
              file=sys.stderr)
        return 2
    fields: dict = {"executor": args.target}
    if args.action == "apply":
        try:
            fields = {"config": Path(args.target).read_text(encoding="utf-8")}
        except OSError as exc:
            print(f"robion ctl apply: cannot read {args.target}: {exc.strerror}", file=sys.stderr)
            return 2
        except UnicodeDecodeError:  # a binary file named by mistake: not a config
            print(f"robion ctl apply: cannot read {args.target}: not a UTF-8 text file", file=sys.stderr)
            return 2
    # The status first, for every action: an apply, drain or resume is answered once the plane has re-solved the
    # traffic plan, up to its solve time limit (an apply: the applied file's, where longer), twice where no plan
    # keeps the headroom and it plans to the full limits. The limit is the one the plane runs (an apply may have
    # changed it since this file was written); a plane that does not answer is reported at once, not after that wait.
    reply = control_request(address, "status", timeout_s=2.0)
    live = reply.get("status") if reply is not None and reply.get("kind") == "status" else None
    if args.action == "status" or reply is None:
        if reply is None:
            print(f"control plane at {address} does not answer", file=sys.stderr)
            return 1
        if not isinstance(live, dict):
            print(f"robion ctl status: {reply.get('message', reply.get('kind'))}", file=sys.stderr)
            return 1
        print(json.dumps(live, indent=2))
        return 0
    solve_s = ((live if isinstance(live, dict) else {}).get("control") or {}).get("solve_time_limit_s")
    solve_s = float(solve_s) if solve_time_limit(solve_s) else cfg.control.solve_time_limit_s
    if args.action == "apply":
        solve_s = max(solve_s, applied_solve_limit(fields["config"]))
    reply = control_request(address, args.action, timeout_s=ANSWER_MARGIN_S + 2 * solve_s, **fields)
    if reply is None:
        print(f"control plane at {address} does not answer", file=sys.stderr)
        return 1
    if reply.get("kind") == "error":
        print(f"robion ctl {args.action}: {reply.get('message')}", file=sys.stderr)
        return 1
    if args.action != "apply":
        print(f"{args.action} {args.target}: routing table v{reply.get('version')}")
        if reply.get("unrouted"):
            print(f"warning: no other executor serves {', '.join(reply['unrouted'])}: their requests are answered "
                  f"UNAVAILABLE until `robion ctl resume {args.target}`", file=sys.stderr)
        return 0
    print(f"applied: routing table v{reply['version']}; executors to reload in turn: {reply['steps'] or 'none'}")
    for name, models in (reply.get("unhosted") or {}).items():
        print(f"warning: while {name} reloads, no other executor serves {', '.join(models)}: "
              "their requests are answered UNAVAILABLE until it is back", file=sys.stderr)
    for name, models in (reply.get("awaiting") or {}).items():
        print(f"warning: {name} drops {', '.join(models)} only once another executor serves them, and their new hosts "
              f"are not registered or are drained: start or resume one; {name}'s step waits up to "
              f"{reply.get('host_wait_s', 300):g} s for it once its turn comes, then fails and keeps them",
              file=sys.stderr)
    if not args.wait:
        return 0
    end = time.monotonic() + args.timeout
    while time.monotonic() < end:
        status = control_status(address, timeout_s=2.0)
        if status is None:  # not answering for a moment (a long solve); the wait goes on
            time.sleep(0.2)
            continue
        rollout = status.get("apply") or {}
        if rollout.get("id") != reply.get("rollout"):
            # The control plane restarted (it knows only its file and applies nothing until an apply of its own),
            # or another apply followed this one: nothing says how this one ended.
            print("placement change: the control plane no longer knows this apply (it restarted, or another apply "
                  "followed); its outcome is unknown: see `robion ctl status`, and apply the file again to be sure",
                  file=sys.stderr)
            return 1
        if not rollout.get("pending"):
            print(f"placement change done: reloaded {rollout.get('done', [])}"
                  + (f", FAILED {rollout['failed']}" if rollout.get("failed") else ""))
            return 1 if rollout.get("failed") else 0
        time.sleep(0.2)
    print(f"placement change still running after {args.timeout:.0f} s", file=sys.stderr)
    return 1


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="robion", description="Serve VLA models to fleets of robots.")
    p.add_argument("--log-level", type=log_level, default=os.environ.get("ROBION_LOG_LEVEL", "WARNING"))
    sub = p.add_subparsers(dest="cmd", required=True)

    up = sub.add_parser("up", help="start router, control plane and executors as local processes")
    up.add_argument("-c", "--config", required=True)
    up.add_argument("--timeout", type=positive_seconds, default=300.0,
                    help="seconds to wait for the cluster to be ready")
    up.add_argument("--max-restarts", type=non_negative_int, default=5, metavar="N",
                    help="start a service that fails (exit code other than 0 and 2, or killed) again, after 1 s "
                         "doubling with each failure (at most 30 s), up to N times within 300 s (default 5; 0: never)")
    up.set_defaults(fn=cmd_up)

    demo = sub.add_parser("demo", help="start a cluster, drive a simulated fleet against it, print the SLO report")
    demo.add_argument("-c", "--config", default=str(DEFAULT_DEMO))
    demo.add_argument("--timeout", type=positive_seconds, default=300.0)
    demo.add_argument("--json", metavar="FILE", help="also write the fleet report as JSON")
    demo.set_defaults(fn=cmd_demo)

    models = sub.add_parser("models", help="list the registered VLA architectures")
    models.add_argument("--json", action="store_true", help="machine-readable output")
    models.add_argument("--size", default="full", help="config size to describe (default: full)")
    models.set_defaults(fn=cmd_models)

    plan = sub.add_parser("plan", help="solve robot-to-GPU assignment without starting anything", add_help=False)
    plan.add_argument("rest", nargs=argparse.REMAINDER)
    plan.set_defaults(fn=cmd_plan)

    bench = sub.add_parser("bench", help="run a benchmark from bench/ (" + ", ".join(sorted(BENCHMARKS)) + ")",
                           add_help=False)
    bench.add_argument("name", nargs="?", choices=sorted(BENCHMARKS))
    bench.add_argument("rest", nargs=argparse.REMAINDER)
    bench.set_defaults(fn=cmd_bench)

    ctl = sub.add_parser("ctl", help="talk to a running cluster's control plane")
    ctl.add_argument("action", choices=["status", "apply", "drain", "resume"],
                     help="status; apply FILE (new placement/populations); drain/resume EXECUTOR")
    ctl.add_argument("target", nargs="?", help="config file for apply, executor name for drain/resume")
    ctl.add_argument("-c", "--config", required=True, help="the running cluster's config (control-plane address)")
    ctl.add_argument("--no-wait", dest="wait", action="store_false", help="apply: return once accepted")
    ctl.add_argument("--timeout", type=positive_seconds, default=600.0,
                     help="apply: seconds to wait for the placement change to finish")
    ctl.set_defaults(fn=cmd_ctl)

    # `plan` and `bench` hand what follows them to their own parsers. argparse keeps an option-like first
    # argument (`robion plan --help`) out of a REMAINDER, so it comes back here as an unknown one.
    args, unknown = p.parse_known_args(argv)
    if args.cmd == "ctl" and args.target is None and len(unknown) == 1 and not unknown[0].startswith("-"):
        # argparse fills `action target?` in one go: with an option between them (`ctl apply --no-wait new.yaml`)
        # the target is left over here.
        args.target = unknown.pop()
    if unknown:
        if args.cmd not in ("plan", "bench"):
            p.error(f"unrecognized arguments: {' '.join(unknown)}")
        args.rest = unknown + args.rest
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s robion %(levelname)s %(message)s")
    try:
        return args.fn(args)
    except BrokenPipeError:
        # The reader left (`robion models --json | head -2`): what is left to print has nowhere to go. Python's
        # recipe: point stdout at /dev/null, so its flush at exit does not raise again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
