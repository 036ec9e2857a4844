"""Thousands of malformed messages against the real router and executor processes."""

import os
import subprocess
import sys

import msgpack
import numpy as np
import zmq

from shared.cluster import LocalCluster
from shared.config import load_config
from shared.protocol import ErrorCode, InferRequest, decode, encode, pack_header
from tests.helpers import cluster_config

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return 0.0


def valid(rid: str, rng) -> list[bytes]:
    return [bytes(f) for f in encode(InferRequest(
        id=rid, robot="fuzz", model="toy-a", instruction="pick",
        images={c: rng.integers(0, 256, (64, 64, 3), dtype=np.uint8) for c in ("cam0", "cam1")},
        state=rng.standard_normal(8).astype(np.float32)))]


def retag(frames, rid, fn):
    h = msgpack.unpackb(frames[0])
    h["id"] = rid
    fn(h)
    return [pack_header(h), *frames[1:]]


def cases(rng, limit, unknown_model: ErrorCode = ErrorCode.UNKNOWN_MODEL):
    """(frames, expected code, expected reply id); the id is "" when the header cannot be read.

    ``unknown_model``: the answer to a model the cluster does not serve. The router's is UNKNOWN_MODEL; an
    executor is sent only models of the router's table, so to it such a model is one routed by an older
    table, and its answer is UNAVAILABLE (retry)."""
    B, S, U, T = ErrorCode.BAD_REQUEST, ErrorCode.SHAPE_MISMATCH, unknown_model, ErrorCode.TOO_LARGE
    kinds = [
        lambda r: ([rng.bytes(int(rng.integers(1, 200)))], B, None),  # random bytes (may decode to a non-map)
        lambda r: ([b"\xc1" + rng.bytes(20)], B, ""),  # never valid msgpack
        lambda r: ([msgpack.packb([1, "x"])], B, ""),
        lambda r: ([pack_header({"kind": "infer", "id": r})], B, r),  # no robot/model/obs
        lambda r: (retag(valid(r, rng), r, lambda h: h.update(model=["x"])), B, r),
        lambda r: (retag(valid(r, rng), r, lambda h: h.update(model="ghost")), U, r),
        lambda r: (retag(valid(r, rng), r, lambda h: h.pop("obs")), B, r),
        lambda r: (retag(valid(r, rng), r, lambda h: h["obs"].update(state=5)), B, r),
        lambda r: (retag(valid(r, rng), r, lambda h: h["obs"]["images"]["cam0"].update(dtype="float64", shape=[64, 64, 3, 1])), B, r),
        lambda r: (retag(valid(r, rng), r, lambda h: h["obs"]["images"]["cam0"].update(shape=[2**31 - 1] * 3)), B, r),
        lambda r: (retag(valid(r, rng), r, lambda h: h["obs"]["images"]["cam0"].update(frame=9)), B, r),
        lambda r: (valid(r, rng) + [b"surplus"], B, r),  # header/frame count mismatch
        lambda r: (valid(r, rng)[:2], B, r),
        lambda r: (retag([valid(r, rng)[0], np.zeros((32, 32, 3), np.uint8).tobytes(), valid(r, rng)[2]], r,
                         lambda h: h["obs"]["images"]["cam0"].update(shape=[32, 32, 3])), S, r),  # wrong size for the model
        lambda r: (retag([valid(r, rng)[0], np.zeros((64, 64, 3), np.float32).tobytes(), valid(r, rng)[2]], r,
                         lambda h: h["obs"]["images"]["cam0"].update(dtype="float32")), S, r),  # wrong dtype for the model
        lambda r: (retag(valid(r, rng), r, lambda h: h["obs"].update(images={"cam0": h["obs"]["images"]["cam0"]})), B, r),
    ]
    i = 0
    while True:
        rid = f"f{i}"
        if i % 10 == 0:
            yield valid(rid, rng), None, rid
        elif i % 500 == 7:
            yield [pack_header({"v": 1, "kind": "infer", "id": rid, "robot": "x", "model": "toy-a", "obs": {}}),
                   b"\0" * (limit + 1)], T, rid
        else:
            frames, code, expect = kinds[i % len(kinds)](rid)
            yield frames, code, expect
        i += 1


def expected_id(frames, expect):
    if expect is not None:
        return expect
    try:
        h = msgpack.unpackb(frames[0])
        return str(h.get("id", "")) if isinstance(h, dict) and isinstance(h.get("id", ""), (str, int)) else ""
    except Exception:
        return ""


def test_router_and_executor_survive_junk(tmp_path):
    path, data = cluster_config(tmp_path, executors=[{"name": "ex0", "device": "cpu", "models": ["toy-a", "toy-b"]}],
                                engine={"kind": "monolithic", "max_batch": 2, "max_queue": 4096})
    cfg = load_config(path)
    limit = cfg.router.max_message_bytes
    cluster = LocalCluster(cfg, path, log_level="ERROR")
    cluster.start(timeout_s=120)
    try:
        ctx = zmq.Context.instance()
        sock = ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(cfg.router.bind)
        rng = np.random.default_rng(1234)
        gen = cases(rng, limit)
        pids = {n: p.pid for n, p in cluster.procs.items()}
        rss_before = {}
        total, valid_ok, window = 3000, 0, 50
        for start in range(0, total, window):
            if start == 500:
                rss_before = {n: rss_mb(pid) for n, pid in pids.items()}
            batch = [next(gen) for _ in range(window)]
            for frames, _, _ in batch:
                sock.send_multipart(frames)
            replies = []
            while len(replies) < window:
                assert sock.poll(20000), f"no reply after {start + len(replies)} messages"
                replies.append(decode(sock.recv_multipart()))
            by_id: dict[str, list] = {}
            for rep in replies:
                by_id.setdefault(rep.id, []).append(rep)
            for frames, code, expect in batch:
                rid = expected_id(frames, expect)
                assert by_id.get(rid), f"no reply for {rid!r}"
                rep = by_id[rid].pop(0)
                if code is None and rid == expect:
                    assert not hasattr(rep, "code"), rep
                    valid_ok += 1
                elif expect is not None:
                    assert rep.code == code, (rid, rep)
                else:
                    assert hasattr(rep, "code"), rep  # random bytes: some error, the code depends on the bytes
        assert valid_ok == total // 10
        assert all(cluster.alive().values())
        growth = {n: rss_mb(pid) - rss_before[n] for n, pid in pids.items()}
        assert all(g < 64 for g in growth.values()), growth
        sock.close()
    finally:
        codes = cluster.stop()
    assert all(code == 0 for code in codes.values()), codes


def test_executor_survives_junk_from_its_router(tmp_path):
    """Act as the router: garbage straight into an executor's backend socket."""
    path, _ = cluster_config(tmp_path, executors=[{"name": "ex0", "device": "cpu", "models": ["toy-a", "toy-b"]}])
    cfg = load_config(path)
    ctx = zmq.Context.instance()
    backend = ctx.socket(zmq.ROUTER)
    backend.setsockopt(zmq.LINGER, 0)
    backend.bind(cfg.router.backend)
    proc = subprocess.Popen([sys.executable, "-m", "services.executor.main", "-c", str(path), "--name", "ex0",
                             "--log-level", "ERROR"], cwd=ROOT)
    try:
        assert backend.poll(60000), "executor never connected"
        ident, robot, hello = backend.recv_multipart()
        assert ident == b"ex0" and robot == b""
        rng = np.random.default_rng(7)
        gen = cases(rng, cfg.router.max_message_bytes, unknown_model=ErrorCode.UNAVAILABLE)
        for i in range(600):
            frames, code, expect = next(gen)
            if i % 50 == 3:
                frames = [pack_header({"kind": "hello", "id": f"f{i}"})]  # not for executors
                code, expect = ErrorCode.BAD_REQUEST, f"f{i}"
            backend.send_multipart([b"ex0", f"robot-{i}".encode(), *frames])
            reply = [b"", b""]
            while reply[1] == b"":  # the executor's hello (again when it registers) carries no robot: not an answer
                assert backend.poll(20000), f"no answer to message {i}"
                reply = backend.recv_multipart()
            assert reply[1] == f"robot-{i}".encode()
            msg = decode(reply[2:])
            if code is not None and expect is not None:
                assert msg.code == code, (i, msg)
        assert proc.poll() is None
    finally:
        proc.terminate()
        assert proc.wait(30) == 0
        backend.close()
