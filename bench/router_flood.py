"""One robot floods the router; does a well-behaved robot of the same model still get its answers?

A real cluster (control plane, router, one executor with the tiny toy models on the CPU) serves a
robot that calls toy-a at --hz and waits for each answer, while another connection sends toy-a
requests as fast as it can and never reads its answers. The router runs once with its default
per-robot cap on requests in flight (router.max_in_flight_per_robot) and once without one (a cap
beyond anything the flood reaches); the two alternate over --rounds so both see the same machine.

    python bench/router_flood.py --out bench/results/router_flood_cpu.json
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import yaml
import zmq

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from shared.client import RobionError, RobotClient  # noqa: E402
from shared.cluster import LocalCluster  # noqa: E402
from shared.config import RouterConfig, load_config  # noqa: E402
from shared.files import unwritable, write_atomic  # noqa: E402
from shared.protocol import InferRequest, encode  # noqa: E402
from tests.helpers import cluster_config  # noqa: E402

UNCAPPED = 10**9
SETTINGS = {"capped": RouterConfig().max_in_flight_per_robot, "uncapped": UNCAPPED}


def flood(address: str, frames_of, stop: threading.Event, sent: list[int]) -> None:
    """Send toy-a requests as fast as the socket takes them; never read an answer."""
    sock = zmq.Context.instance().socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(address)
    while not stop.is_set():
        try:
            sock.send_multipart(frames_of(sent[0]), zmq.NOBLOCK)
            sent[0] += 1
        except zmq.Again:
            time.sleep(0.001)
    sock.close()


def one_run(cap: int, requests: int, hz: float) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix="robion-flood-"))
    path, data = cluster_config(tmp, executors=[{"name": "ex0", "device": "cpu", "models": ["toy-a", "toy-b"]}])
    data["router"]["max_in_flight_per_robot"] = cap
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    with LocalCluster(cfg, path, log_level="ERROR"), RobotClient(cfg.router.bind, robot_id="good", timeout_s=5) as good:
        info = good.metadata()["toy-a"]
        images = {cam: np.zeros(info.image_shape, np.uint8) for cam in info.cameras}
        state = np.zeros(info.state_dim, np.float32)
        deadline_s = info.deadline_ms / 1000

        def frames_of(i: int) -> list:
            return encode(InferRequest(id=i, robot="flood", model="toy-a", images=images, state=state))

        stop, sent = threading.Event(), [0]
        flooder = threading.Thread(target=flood, args=(cfg.router.bind, frames_of, stop, sent), daemon=True)
        flooder.start()
        time.sleep(2.0)  # the flood is under way
        outcomes: dict[str, int] = {}
        latencies = []
        for _ in range(requests):
            t0 = time.monotonic()
            try:
                good.infer("toy-a", images, state)
                took = time.monotonic() - t0
                latencies.append(took)
                key = "ok" if took <= deadline_s else "late"
            except RobionError as exc:
                key = exc.code.value
            outcomes[key] = outcomes.get(key, 0) + 1
            time.sleep(max(0.0, 1 / hz - (time.monotonic() - t0)))
        stop.set()
        flooder.join(5)
    lat = np.array(latencies) * 1000 if latencies else np.array([np.nan])
    return {"cap": cap, "flood_sent": sent[0], "good": outcomes, "good_in_deadline": outcomes.get("ok", 0) / requests,
            "good_p50_ms": float(np.percentile(lat, 50)), "good_p99_ms": float(np.percentile(lat, 99)),
            "deadline_ms": info.deadline_ms}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--requests", type=int, default=30, help="the good robot's requests per run")
    p.add_argument("--hz", type=float, default=2.0, help="the good robot's rate")
    p.add_argument("--rounds", type=int, default=2, help="runs of each setting, alternating")
    p.add_argument("--out", default="")
    args = p.parse_args()
    for name, value in (("--requests", args.requests), ("--rounds", args.rounds)):
        if value < 1:
            p.error(f"{name}: expected at least 1, got {value}")
    if not (args.hz > 0 and np.isfinite(args.hz)):
        p.error(f"--hz: expected a positive rate, got {args.hz}")
    if args.out and (why := unwritable(args.out)):
        p.error(f"--out: {why}")
    runs = []
    for r in range(args.rounds):
        for name, cap in SETTINGS.items():
            run = {"setting": name, "round": r, **one_run(cap, args.requests, args.hz)}
            runs.append(run)
            print(f"round {r} {name}: {run['good']}", file=sys.stderr)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout.strip()
    result = {"bench": "router_flood", "date": datetime.date.today().isoformat(), "commit": commit,
              "host": platform.node(), "cores": os.cpu_count(), "requests": args.requests, "hz": args.hz,
              "rounds": args.rounds, "runs": runs, "command": "python bench/router_flood.py " + " ".join(sys.argv[1:])}
    if args.out:
        write_atomic(args.out, json.dumps(result, indent=2) + "\n")
    print(f"{'setting':<10}{'cap':>11}{'round':>6}{'flood sent':>12}{'good in deadline':>18}{'good p50 ms':>13}  answers")
    for run in runs:
        print(f"{run['setting']:<10}{run['cap']:>11}{run['round']:>6}{run['flood_sent']:>12}"
              f"{run['good_in_deadline']:>17.0%}{run['good_p50_ms']:>13.1f}  {run['good']}")


if __name__ == "__main__":
    main()
