"""Per-stage latency of the zoo's full models on one GPU: bf16, CUDA graphs, 2 cameras.

For each model and batch size: seeded weights and inputs, eager warm-up, one CUDA
graph per stage (captured like the engine does: the VLM graph's handoff is the action
graph's input), then many replays timed with CUDA events; median and p99 per stage
and for VLM + action back to back, plus peak GPU memory.

    python bench/model_latency.py --out bench/results/model_latency.json
    python bench/model_latency.py --models pi0 --batches 1 --profile pi0_profile.txt
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from bench.experiments.timing import replay_pair_ms  # noqa: E402
from shared.models import build_model  # noqa: E402
from shared.files import unwritable  # noqa: E402
from shared.models.registry import build_meta  # noqa: E402

TARGETS_MS = {"pi0": 12.0, "groot_n15": 10.0, "xr0": 12.0, "smolvla": 5.0}  # H100, batch 1, VLM + action


def pct(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(q * (len(xs) - 1))))]


def summary(xs: list[float]) -> dict[str, float]:
    return {"median": round(statistics.median(xs), 4), "p99": round(pct(xs, 0.99), 4), "min": round(min(xs), 4)}


def bench_batch(model, batch: int, iters: int, warmup: int) -> dict:
    dev = torch.device("cuda")
    gen = torch.Generator().manual_seed(1234 + batch)
    images, state, tokens = model.example_inputs(batch, device=dev, generator=gen)
    tokens[:, model.io.prompt_len // 2:] = 0  # a realistic half-padded prompt
    noise = model.noise(batch, device=dev, generator=gen).to(torch.bfloat16)

    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):  # warm-up: Triton JIT, cuBLAS heuristics, allocator
        for _ in range(3):
            eager = model.action_stage(model.vlm_stage(images, state, tokens), noise)
    torch.cuda.current_stream().wait_stream(side)

    pool = torch.cuda.graph_pool_handle()
    g_vlm, g_act = torch.cuda.CUDAGraph(), torch.cuda.CUDAGraph()
    with torch.cuda.graph(g_vlm, pool=pool):
        handoff = model.vlm_stage(images, state, tokens)
    with torch.cuda.graph(g_act, pool=pool):
        actions = model.action_stage(handoff, noise)
    g_vlm.replay()
    g_act.replay()
    torch.cuda.synchronize()
    err = (actions.float() - eager.float()).abs().max().item()

    vlm, act, tot = replay_pair_ms(g_vlm, g_act, iters, warmup)
    out = {"vlm_ms": summary(vlm), "action_ms": summary(act), "total_ms": summary(tot),
           "peak_mem_gib": round(torch.cuda.max_memory_allocated() / 2 ** 30, 3),
           "graph_vs_eager_max_abs_diff": err, "finite": bool(torch.isfinite(actions).all().item())}
    del g_vlm, g_act, handoff, actions
    return out


def profile_action(model, path: str) -> None:
    """Kernel-level profile of one eager VLM + action call at batch 1 (what a graph replays)."""
    dev = torch.device("cuda")
    images, state, tokens = model.example_inputs(1, device=dev, generator=torch.Generator().manual_seed(0))
    noise = model.noise(1, device=dev).to(torch.bfloat16)
    for _ in range(2):
        h = model.vlm_stage(images, state, tokens)
        model.action_stage(h, noise)
    torch.cuda.synchronize()
    acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    with open(path, "a") as f:
        for name, fn in (("vlm", lambda: model.vlm_stage(images, state, tokens)),
                         ("action", lambda: model.action_stage(h, noise))):
            with torch.profiler.profile(activities=acts) as prof:
                fn()
                torch.cuda.synchronize()
            kernels = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
            total = sum(e.device_time for e in kernels) / 1000
            f.write(f"\n## {model.arch} {name} stage, batch 1: {len(kernels)} kernels, {total:.3f} ms of kernel time\n")
            f.write(prof.key_averages().table(sort_by="device_time_total", row_limit=25, max_name_column_width=70))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="JSON results path")
    ap.add_argument("--models", default="pi0,smolvla,groot_n15,xr0")
    ap.add_argument("--batches", default="1,2,4")
    ap.add_argument("--iters", type=int, default=200)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--profile", default=None, help="also write a kernel profile (batch 1) to this text file")
    args = ap.parse_args(argv)
    from bench.capacity import dirty, source_commit  # here: capacity imports this module for its overlap bound

    if not torch.cuda.is_available():
        ap.error("needs a CUDA GPU (it times CUDA graph replays)")
    if args.iters < 1 or args.warmup < 0:
        ap.error(f"--iters and --warmup: expected at least 1 and 0, got {args.iters} and {args.warmup}")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    if why := unwritable(args.out):  # before minutes of model building, not after
        ap.error(f"--out: {why}")
    torch.backends.cuda.matmul.allow_tf32 = True
    results = {"gpu": torch.cuda.get_device_name(), "date": datetime.date.today().isoformat(),
               "commit": source_commit(), "dirty": dirty(),
               "torch": torch.__version__, "command": "python " + " ".join([sys.argv[0], *(argv or sys.argv[1:])]),
               "dtype": "bfloat16", "cuda_graphs": True, "models": {}}
    for arch in args.models.split(","):
        t0 = time.time()
        params = build_meta(arch).stage_parameters()
        model = build_model(arch, "full", seed=0, device="cuda")
        weights = torch.cuda.memory_allocated() / 2 ** 30
        res = {"params": params, "cameras": len(model.io.cameras), "weights_gib": round(weights, 3),
               "build_s": round(time.time() - t0, 2), "batches": {}}
        with torch.inference_mode():
            for b in [int(x) for x in args.batches.split(",")]:
                res["batches"][str(b)] = bench_batch(model, b, args.iters, args.warmup)
                torch.cuda.empty_cache()
            if args.profile:
                profile_action(model, args.profile)
        results["models"][arch] = res
        print(f"{arch}: done in {time.time() - t0:.1f} s", file=sys.stderr, flush=True)
        del model
        torch.cuda.empty_cache()
    with open(args.out, "w") as f:
        json.dump(results, f, indent=2)

    print(f"\n{results['gpu']}, {results['date']}, bf16, CUDA graphs; median (p99) ms; peak GiB")
    print(f"{'model':<10} {'b':>2} {'vlm':>16} {'action':>16} {'total':>16} {'peak':>6}  target(b=1)")
    for arch, res in results["models"].items():
        for b, r in res["batches"].items():
            tgt = ""
            if b == "1" and arch in TARGETS_MS:
                ok = r["total_ms"]["median"] <= TARGETS_MS[arch]
                tgt = f"<= {TARGETS_MS[arch]:g} {'met' if ok else 'MISSED'}"
            cell = lambda k: f"{r[k]['median']:7.3f} ({r[k]['p99']:6.3f})"  # noqa: E731
            print(f"{arch:<10} {b:>2} {cell('vlm_ms'):>16} {cell('action_ms'):>16} {cell('total_ms'):>16} "
                  f"{r['peak_mem_gib']:6.2f}  {tgt}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
