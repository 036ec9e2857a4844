"""Host cost of cudaGraphLaunch when the same executable graph is still running (diagnostic).

A graph of N small matmuls is launched; while it runs, the host times a second launch of
(a) the same exec, (b) a separately captured graph of the same body, (c) a second exec
instantiated from the same cudaGraph_t (when torch and cuda.bindings allow it), and (d) a
launch on an idle GPU.

    python bench/graph_relaunch.py --kernels 1000
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kernels", type=int, default=1000, help="matmuls in the graph (runs on cuda:0)")
    ap.add_argument("--reps", type=int, default=30, help="timed launches per case")
    args = ap.parse_args()
    dev = torch.device("cuda:0")
    s = torch.cuda.Stream(dev)
    w = torch.randn(512, 512, device=dev, dtype=torch.bfloat16) * 0.01
    x = torch.randn(16, 512, device=dev, dtype=torch.bfloat16)

    def body():
        y = x
        for _ in range(args.kernels):
            y = y @ w
        x.copy_(y)

    s.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(s):
        body()
    s.synchronize()

    def capture(**kw):
        g = torch.cuda.CUDAGraph(**kw)
        with torch.cuda.graph(g, stream=s):
            body()
        s.synchronize()
        return g

    g1, g2 = capture(), capture()
    launch2 = None
    try:
        from cuda.bindings import runtime as cudart

        g3 = capture(keep_graph=True)
        g3.instantiate()
        err, exec2 = cudart.cudaGraphInstantiate(g3.raw_cuda_graph(), 0)
        assert int(err) == 0, err
        err, = cudart.cudaGraphUpload(exec2, s.cuda_stream)
        launch2 = (g3, exec2, cudart)
    except Exception as exc:  # noqa: BLE001
        print("second exec from one cudaGraph_t unavailable:", repr(exc))

    torch.cuda.set_stream(s)
    t0 = time.perf_counter()
    g1.replay()
    s.synchronize()
    print(f"graph of {args.kernels} matmuls runs {1e3 * (time.perf_counter() - t0):.2f} ms")

    def timed(first, second) -> float:
        costs = []
        for _ in range(args.reps):
            if first is not None:
                first()
            t = time.perf_counter()
            second()
            costs.append((time.perf_counter() - t) * 1e6)
            s.synchronize()
        return float(np.median(costs[3:])), float(np.max(costs[3:]))

    rows = {
        "idle GPU": timed(None, g1.replay),
        "same exec in flight": timed(g1.replay, g1.replay),
        "other capture in flight": timed(g1.replay, g2.replay),
    }
    if launch2 is not None:
        g3, exec2, cudart = launch2
        rows["2nd exec of same graph in flight"] = timed(g3.replay, lambda: cudart.cudaGraphLaunch(exec2, s.cuda_stream))
        rows["2nd exec, idle"] = timed(None, lambda: cudart.cudaGraphLaunch(exec2, s.cuda_stream))
    torch.cuda.set_stream(torch.cuda.default_stream())
    for k, (med, mx) in rows.items():
        print(f"{k:<36} launch {med:8.1f} us median, {mx:8.1f} max")


if __name__ == "__main__":
    main()
