"""What the router hop adds to a request: direct executor access vs through the real router.

The request carries two 224x224x3 uint8 images (301 KB) and gets a 50x32 float32 action
chunk back. Both paths end at the same echo responder code (decode the header, send the
chunk), so the difference is the router process: one more receive and send of every frame
plus the routing-table lookup. Direct and routed requests alternate so both see the same
machine noise.

    python bench/router_hop.py --out bench/results/router_hop.json
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
import time

import numpy as np
import yaml
import zmq

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from shared import control  # noqa: E402
from shared.files import unwritable  # noqa: E402
from shared.protocol import (InferReply, InferRequest, ModelInfo, decode, encode, header_id,  # noqa: E402
                             unpack_header)
from tests.helpers import free_ports  # noqa: E402

ACTIONS = np.zeros((50, 32), np.float32)
INFO = ModelInfo(cameras=["base", "wrist"], image_shape=[224, 224, 3], state_dim=32, horizon=50, action_dim=32,
                 deadline_ms=156.0, arch="echo")


def echo_reply(body: list) -> list:
    rid = header_id(unpack_header(body[0]))
    return encode(InferReply(id=rid, model="echo", actions=ACTIONS))


def serve_direct(address: str) -> None:
    """A ROUTER socket robots talk to directly: the 'no router' baseline."""
    sock = zmq.Context.instance().socket(zmq.ROUTER)
    sock.bind(address)
    while True:
        frames = sock.recv_multipart(copy=False)
        sock.send_multipart([frames[0], *echo_reply([f.buffer for f in frames[1:]])], copy=False)


def serve_executor(cfg_path: str) -> None:
    """An executor as the router sees it: registers, then answers through the backend socket."""
    cfg = yaml.safe_load(open(cfg_path))
    ctx = zmq.Context.instance()
    ctl = ctx.socket(zmq.DEALER)
    ctl.connect(cfg["control"]["bind"])
    ctl.send(control.pack("register", executor="echo0", device="cpu", models={"echo": INFO.to_wire()}))
    back = ctx.socket(zmq.DEALER)
    back.setsockopt(zmq.IDENTITY, b"echo0")
    back.connect(cfg["router"]["backend"])
    back.send_multipart([b"", control.pack("executor_hello", executor="echo0")])
    poller = zmq.Poller()
    poller.register(back, zmq.POLLIN)
    last = time.monotonic()
    while True:
        if poller.poll(100):
            frames = back.recv_multipart(copy=False)
            back.send_multipart([frames[0], *echo_reply([f.buffer for f in frames[1:]])], copy=False)
        if time.monotonic() - last > 0.2:
            last = time.monotonic()
            ctl.send(control.pack("heartbeat", executor="echo0", depths={}))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--iters", type=int, default=3000)
    p.add_argument("--warmup", type=int, default=300)
    p.add_argument("--out", default="")
    p.add_argument("--role", choices=["direct", "executor"], help=argparse.SUPPRESS)
    p.add_argument("--addr", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.iters < 1 or args.warmup < 0:  # an IndexError after the whole run, before
        p.error(f"--iters and --warmup: expected at least 1 and 0, got {args.iters} and {args.warmup}")
    if args.out and (why := unwritable(args.out)):  # before the run, not after it
        p.error(f"--out: {why}")
    if args.role == "direct":
        return serve_direct(args.addr)
    if args.role == "executor":
        return serve_executor(args.addr)

    rp, bp, cp, dp = free_ports(4)
    tmp = tempfile.mkdtemp()
    cfg = {"models": [{"name": "echo", "arch": "toy"}], "executors": [{"name": "echo0", "models": ["echo"]}],
           "router": {"bind": f"tcp://127.0.0.1:{rp}", "backend": f"tcp://127.0.0.1:{bp}"},
           "control": {"bind": f"tcp://127.0.0.1:{cp}", "heartbeat_s": 0.2}}
    cfg_path = os.path.join(tmp, "hop.yaml")
    with open(cfg_path, "w") as fh:
        yaml.safe_dump(cfg, fh)
    env = {**os.environ, "PYTHONPATH": ROOT}
    procs = [subprocess.Popen([sys.executable, "-m", "services.controlplane.main", "-c", cfg_path, "--log-level", "ERROR"], env=env, cwd=ROOT),
             subprocess.Popen([sys.executable, "-m", "services.router.main", "-c", cfg_path, "--log-level", "ERROR"], env=env, cwd=ROOT),
             subprocess.Popen([sys.executable, __file__, "--role", "executor", "--addr", cfg_path], env=env),
             subprocess.Popen([sys.executable, __file__, "--role", "direct", "--addr", f"tcp://127.0.0.1:{dp}"], env=env)]
    try:
        ctx = zmq.Context.instance()
        routed = ctx.socket(zmq.DEALER)
        routed.connect(f"tcp://127.0.0.1:{rp}")
        direct = ctx.socket(zmq.DEALER)
        direct.connect(f"tcp://127.0.0.1:{dp}")
        rng = np.random.default_rng(0)
        images = {c: rng.integers(0, 256, (224, 224, 3), dtype=np.uint8) for c in INFO.cameras}
        state = rng.standard_normal(32).astype(np.float32)

        def once(sock, rid: str) -> float:
            frames = encode(InferRequest(id=rid, robot="bench", model="echo", images=images, state=state,
                                         instruction="pick up the cup"))
            t0 = time.perf_counter()
            sock.send_multipart(frames, copy=False)
            if not sock.poll(5000):
                raise TimeoutError(rid)
            reply = decode(sock.recv_multipart())
            dt = time.perf_counter() - t0
            if not isinstance(reply, InferReply):
                raise RuntimeError(f"{rid}: {reply}")
            return dt

        end = time.monotonic() + 60  # wait until the router has the executor in its table
        while True:
            try:
                once(routed, "probe")
                break
            except (RuntimeError, TimeoutError):
                if time.monotonic() > end:
                    raise
                time.sleep(0.2)
        samples: dict[str, list[float]] = {"direct": [], "routed": []}
        for i in range(args.warmup + args.iters):
            order = ("direct", "routed") if i % 2 == 0 else ("routed", "direct")
            for name in order:
                dt = once(direct if name == "direct" else routed, f"{name}-{i}")
                if i >= args.warmup:
                    samples[name].append(dt * 1e6)
    finally:
        for pr in procs:
            pr.terminate()
        for pr in procs:
            pr.wait(10)

    stats = {name: {"p50_us": float(np.percentile(v, 50)), "p99_us": float(np.percentile(v, 99)),
                    "mean_us": float(np.mean(v)), "n": len(v)} for name, v in samples.items()}
    hop = {"p50_us": stats["routed"]["p50_us"] - stats["direct"]["p50_us"],
           "p99_us": stats["routed"]["p99_us"] - stats["direct"]["p99_us"]}
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout.strip()
    result = {"bench": "router_hop", "date": datetime.date.today().isoformat(), "commit": commit,
              "host": platform.node(), "cpu": _cpu(), "cores": os.cpu_count(), "request_bytes": 2 * 224 * 224 * 3 + 128,
              "iters": args.iters, "warmup": args.warmup, "paths": stats, "router_hop": hop,
              "command": "python bench/router_hop.py " + " ".join(sys.argv[1:])}
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(result, fh, indent=2)
    print(f"{'path':<8}{'p50 us':>10}{'p99 us':>10}{'mean us':>10}")
    for name, s in stats.items():
        print(f"{name:<8}{s['p50_us']:>10.0f}{s['p99_us']:>10.0f}{s['mean_us']:>10.0f}")
    print(f"router hop adds {hop['p50_us']:.0f} us at p50, {hop['p99_us']:.0f} us at p99 ({args.iters} requests each, {os.cpu_count()} cores)")


def _cpu() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


if __name__ == "__main__":
    main()
