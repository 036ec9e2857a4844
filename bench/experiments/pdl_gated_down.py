"""Experiment (not on main): programmatic dependent launch and the gated activation inside
the down projection, A/B against main's kernels for pi0 and SmolVLA at batch 1 and 2.

Needs the kernel changes in pdl_gated_down.patch (fused.py: a PDL switch for the Triton
kernels, ``linear_residual_splitk(..., act=)``; the two action experts use it):

    git apply bench/experiments/pdl_gated_down.patch
    OUT=/tmp python bench/experiments/pdl_gated_down.py

Four variants per model and batch, each a VLM graph + action graph, replays interleaved:
before (main), gated, pdl, pdl+gated. Results: docs/RESULTS.md (model zoo, "Tried and not
kept"); raw JSON bench/results/kernel_exp_pdl_gated_h100.json.
"""
import json
import os
import statistics
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from shared.models import build_model, fused, layers, smolvla  # noqa: E402

OUT = os.environ.get("OUT", "/tmp")
ORIG = fused.linear_residual_splitk
SEP = {"on": False}


def splitk(x, w, b, r, ws, act=None):
    if act is not None and SEP["on"]:
        x, act = fused.gated_act(x, act), None
    return ORIG(x, w, b, r, ws, act=act)


layers.linear_residual_splitk = splitk
smolvla.linear_residual_splitk = splitk

VARIANTS = {"before": (False, True), "gated": (False, False), "pdl": (True, True), "pdl+gated": (True, False)}


def run(arch, batch, iters):
    dev = torch.device("cuda")
    model = build_model(arch, "full", device=dev, seed=0)
    gen = torch.Generator().manual_seed(1234 + batch)
    images, state, tokens = model.example_inputs(batch, device=dev, generator=gen)
    tokens[:, model.io.prompt_len // 2:] = 0
    noise = model.noise(batch, device=dev, generator=gen).to(torch.bfloat16)
    graphs, outs = {}, {}
    pool = torch.cuda.graph_pool_handle()
    for name, (pdl, sep) in VARIANTS.items():
        fused.set_pdl(pdl)
        SEP["on"] = sep
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(2):
                model.action_stage(model.vlm_stage(images, state, tokens), noise)
        torch.cuda.current_stream().wait_stream(side)
        gv, ga = torch.cuda.CUDAGraph(), torch.cuda.CUDAGraph()
        with torch.cuda.graph(gv, pool=pool):
            h = model.vlm_stage(images, state, tokens)
        with torch.cuda.graph(ga, pool=pool):
            a = model.action_stage(h, noise)
        gv.replay()
        ga.replay()
        torch.cuda.synchronize()
        graphs[name], outs[name] = (gv, ga), a
    fused.set_pdl(True)
    SEP["on"] = False
    same = {k: bool(torch.equal(v, outs["before"])) for k, v in outs.items()}
    for _ in range(20):
        for gv, ga in graphs.values():
            gv.replay()
            ga.replay()
    ev = {k: [] for k in graphs}
    torch.cuda.synchronize()
    for _ in range(iters):
        for k, (gv, ga) in graphs.items():
            e = [torch.cuda.Event(enable_timing=True) for _ in range(3)]
            e[0].record()
            gv.replay()
            e[1].record()
            ga.replay()
            e[2].record()
            ev[k].append(e)
    torch.cuda.synchronize()
    res = {}
    for k, es in ev.items():
        v = sorted(a.elapsed_time(b) for a, b, _ in es)
        a = sorted(b.elapsed_time(c) for _, b, c in es)
        t = sorted(a_.elapsed_time(c) for a_, _, c in es)
        res[k] = {"vlm": statistics.median(v), "action": statistics.median(a), "total": statistics.median(t),
                  "total_p99": t[int(0.99 * (len(t) - 1))], "same_as_before": same[k]}
    del graphs, outs, model
    torch.cuda.empty_cache()
    return res


def main():
    out = {"gpu": torch.cuda.get_device_name(), "torch": torch.__version__, "pdl_available": fused._HAS_GDC}
    import triton
    out["triton"] = triton.__version__
    rows = []
    for arch in os.environ.get("AB_MODELS", "pi0,smolvla").split(","):
        for b in (1, 2):
            r = run(arch, b, int(os.environ.get("AB_ITERS", 200)))
            out[f"{arch}_b{b}"] = r
            for k, v in r.items():
                rows.append((arch, b, k, v))
            print(f"done {arch} b={b}", flush=True)
    with open(os.path.join(OUT, "ab.json"), "w") as f:
        json.dump(out, f, indent=1)
    print(f"{out['gpu']} torch {out['torch']} triton {out['triton']}")
    print(f"{'model':8s} {'b':>2s} {'variant':10s} {'vlm':>7s} {'action':>7s} {'total':>7s} {'p99':>7s} same")
    for arch, b, k, v in rows:
        print(f"{arch:8s} {b:2d} {k:10s} {v['vlm']:7.3f} {v['action']:7.3f} {v['total']:7.3f} {v['total_p99']:7.3f} "
              f"{v['same_as_before']}")


if __name__ == "__main__":
    main()
