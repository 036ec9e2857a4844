"""Experiment (not used by the models): does prefetching weights into L2 speed up pi0's action stage?

Two parts, H100, bf16, CUDA graphs:
1. micro: 18 GEMMs of one action-expert shape (QKV, gate/up on cuBLAS; o, down on the split-K
   Triton kernel) with distinct weights ("cold", streamed from HBM), with the next GEMM's
   weights prefetched on a side branch of the graph (``cp.async.bulk.prefetch.L2`` or plain
   loads), and with one weight repeated ("hot", L2-resident): the most any prefetch can gain.
2. the whole pi0 action stage at batch 1 with the same prefetches issued one layer or one
   to three GEMMs ahead (side branch), or inline on the stage's own stream.
Results: docs/RESULTS.md (model zoo, "Tried and not kept"); raw JSON
bench/results/kernel_exp_l2_prefetch_h100.json.

    OUT=/tmp python bench/experiments/l2_prefetch.py
"""
import json
import os
import statistics
import sys

import torch
import torch.nn.functional as F
import triton
import triton.language as tl

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from shared.models import build_model  # noqa: E402
from shared.models import fused, layers  # noqa: E402
from shared.models.layers import attention, gated_act, linear_residual_splitk  # noqa: E402

OUT = os.environ.get("OUT", "/tmp")
CHUNK = int(os.environ.get("PF_CHUNK", 32768))


@triton.jit
def _bulk_prefetch_kernel(ptr, nbytes, CHUNK: tl.constexpr, BLOCK: tl.constexpr):
    offs = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    start = offs.to(tl.int64) * CHUNK
    size = tl.minimum(nbytes - start, CHUNK)
    ok = size > 0
    start = tl.where(ok, start, 0)
    size = tl.where(ok, size, 16).to(tl.int32)
    addr = (ptr + start).to(tl.int64)
    tl.inline_asm_elementwise("cp.async.bulk.prefetch.L2.global [$1], $2;\n\tmov.u32 $0, 0;", "=r,l,r",
                              [addr, size], dtype=tl.int32, is_pure=False, pack=1)


@triton.jit
def _load_prefetch_kernel(ptr, n, sink, BLOCK: tl.constexpr, ITERS: tl.constexpr):
    pid = tl.program_id(0)
    acc = tl.zeros([BLOCK], dtype=tl.int32)
    for i in range(ITERS):
        offs = (pid * ITERS + i).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
        acc += tl.load(ptr + offs, mask=offs < n, other=0, eviction_policy="evict_last")
    s = tl.sum(acc, 0)
    tl.store(sink + pid, s, mask=s == 123456789)


SINK = None


def prefetch(w: torch.Tensor, mode: str = "bulk") -> None:
    global SINK
    if mode == "bulk":
        b = w.view(-1).view(torch.uint8)
        n = b.numel()
        lanes = triton.cdiv(n, CHUNK)
        block = 128
        _bulk_prefetch_kernel[(triton.cdiv(lanes, block),)](b, n, CHUNK=CHUNK, BLOCK=block, num_warps=4)
    else:
        b = w.view(-1).view(torch.int32)
        n = b.numel()
        block, iters = 1024, 16
        if SINK is None:
            SINK = torch.zeros(65536, dtype=torch.int32, device=w.device)
        _load_prefetch_kernel[(triton.cdiv(n, block * iters),)](b, n, SINK, BLOCK=block, ITERS=iters, num_warps=8)


PF_STREAM = None
CFG = {"mode": None, "ahead": 0, "inline": False, "kind": "bulk"}
ORDER: list[torch.Tensor] = []
POS = {}


def issue(ws_list):
    if not ws_list:
        return
    if CFG["inline"]:
        for w in ws_list:
            prefetch(w, CFG["kind"])
        return
    main = torch.cuda.current_stream()
    PF_STREAM.wait_stream(main)
    STATE["forked"] = True
    with torch.cuda.stream(PF_STREAM):
        for w in ws_list:
            prefetch(w, CFG["kind"])


def ahead_of(w: torch.Tensor, k: int, step_last: bool):
    i = POS[w.data_ptr()]
    out = []
    for j in range(1, k + 1):
        if i + j < len(ORDER):
            out.append(ORDER[(i + j)])
        elif not step_last:
            out.append(ORDER[(i + j) % len(ORDER)])
    return out


STATE = {"last_step": False}


def forward_fused(self, x, k_out, v_out, rope, bias, k_all, v_all, ws):
    k = CFG["ahead"]
    if CFG["mode"] == "layer" and POS.get(self.attn.qkv.weight.data_ptr()) is not None:
        i = POS[self.attn.qkv.weight.data_ptr()] // 4
        nl = len(ORDER) // 4
        if i + 1 < nl or not STATE["last_step"]:
            j = (i + 1) % nl
            issue(ORDER[4 * j:4 * j + 4])
    if CFG["mode"] == "gemm":
        issue(ahead_of(self.attn.qkv.weight, k, STATE["last_step"]))
    q = self.attn.project(self.attn_norm(x), k_out, v_out, rope)
    kk = k_out if k_all is None else k_all
    vv = v_out if v_all is None else v_all
    if CFG["mode"] == "gemm":
        issue(ahead_of(self.attn.o.weight, k, STATE["last_step"]))
    x = linear_residual_splitk(attention(q, kk, vv, bias, ws), self.attn.o.weight, self.attn.o.bias, x, ws)
    if CFG["mode"] == "gemm":
        issue(ahead_of(self.mlp.gate_up.weight, k, STATE["last_step"]))
    h = gated_act(self.mlp.gate_up(self.mlp_norm(x)), self.mlp.act)
    if CFG["mode"] == "gemm":
        issue(ahead_of(self.mlp.down.weight, k, STATE["last_step"]))
    return linear_residual_splitk(h, self.mlp.down.weight, self.mlp.down.bias, x, ws)


def timed(graphs: dict, reps: int, warm: int = 20) -> dict:
    for _ in range(warm):
        for g in graphs.values():
            g.replay()
    res = {k: [] for k in graphs}
    torch.cuda.synchronize()
    for r in range(reps):
        for k, g in graphs.items():
            e0, e1 = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            e0.record()
            g.replay()
            e1.record()
            res[k].append((e0, e1))
    torch.cuda.synchronize()
    out = {}
    for k, evs in res.items():
        xs = sorted(a.elapsed_time(b) for a, b in evs)
        out[k] = {"median": statistics.median(xs), "p99": xs[int(0.99 * (len(xs) - 1))], "min": xs[0]}
    return out


def micro(dev):
    """18 distinct GEMMs of one shape in a graph: cold (HBM), prefetched, and hot (one weight repeated)."""
    res = {}
    torch.manual_seed(0)
    shapes = {"qkv": (2560, 1024), "gate_up": (8192, 1024), "down": (1024, 4096), "o": (1024, 2048)}
    ws = fused.Workspace(dev)
    for name, (n, kdim) in shapes.items():
        W = [torch.randn(n, kdim, device=dev, dtype=torch.bfloat16) * 0.02 for _ in range(18)]
        x = torch.randn(51, kdim, device=dev, dtype=torch.bfloat16)
        r = torch.randn(51, n, device=dev, dtype=torch.bfloat16)
        splitk = name in ("down", "o")

        def op(w):
            return linear_residual_splitk(x, w, None, r, ws) if splitk else F.linear(x, w)

        graphs = {}
        for variant in ("cold", "pf1", "pf1_load", "hot"):
            for _ in range(2):
                for i in range(18):
                    if variant.startswith("pf"):
                        prefetch(W[(i + 1) % 18], "load" if variant.endswith("load") else "bulk")
                    op(W[0] if variant == "hot" else W[i])
            torch.cuda.synchronize()
            g = torch.cuda.CUDAGraph()
            with torch.cuda.graph(g):
                main = torch.cuda.current_stream()
                for i in range(18):
                    if variant.startswith("pf") and i + 1 < 18:
                        PF_STREAM.wait_stream(main)
                        with torch.cuda.stream(PF_STREAM):
                            prefetch(W[i + 1], "load" if variant.endswith("load") else "bulk")
                    op(W[0] if variant == "hot" else W[i])
                if variant.startswith("pf"):
                    main.wait_stream(PF_STREAM)
            graphs[variant] = g
        t = timed(graphs, 100)
        res[name] = {k: round(v["median"] * 1000 / 18, 2) for k, v in t.items()}
        print(f"micro {name:8s} us/GEMM " + " ".join(f"{k}={v}" for k, v in res[name].items()), flush=True)
    return res


def main():
    global PF_STREAM
    dev = torch.device("cuda")
    PF_STREAM = torch.cuda.Stream()
    out = {"gpu": torch.cuda.get_device_name(), "chunk": CHUNK}
    out["micro"] = micro(dev)

    model = build_model("pi0", "full", device=dev, dtype=torch.bfloat16, seed=0)
    e = model.expert
    for lyr in e.layers:
        for w in (lyr.attn.qkv.weight, lyr.attn.o.weight, lyr.mlp.gate_up.weight, lyr.mlp.down.weight):
            POS[w.data_ptr()] = len(ORDER)
            ORDER.append(w)
    layers.DecoderLayer.forward_fused = forward_fused
    gen = torch.Generator().manual_seed(1234)
    images, state, tokens = model.example_inputs(1, device=dev, generator=gen)
    tokens[:, model.io.prompt_len // 2:] = 0
    noise = model.noise(1, device=dev, generator=gen).to(torch.bfloat16)
    handoff = model.vlm_stage(images, state, tokens)
    orig = type(model).action_stage
    steps = model.cfg.steps

    # mark the last Euler step: wrap expert layer loop by counting layer calls
    calls = {"n": 0}
    nl = len(e.layers)

    def patched_stage(handoff, noise):
        calls["n"] = 0
        STATE["forked"] = False
        a = orig(model, handoff, noise)
        if STATE["forked"]:
            torch.cuda.current_stream().wait_stream(PF_STREAM)
        return a

    orig_fwd = forward_fused

    def counting_fwd(self, *a, **k):
        STATE["last_step"] = calls["n"] >= (steps - 1) * nl
        calls["n"] += 1
        return orig_fwd(self, *a, **k)

    layers.DecoderLayer.forward_fused = counting_fwd

    variants = {
        "base": dict(mode=None, ahead=0, inline=False, kind="bulk"),
        "layer": dict(mode="layer", ahead=0, inline=False, kind="bulk"),
        "gemm1": dict(mode="gemm", ahead=1, inline=False, kind="bulk"),
        "gemm2": dict(mode="gemm", ahead=2, inline=False, kind="bulk"),
        "gemm3": dict(mode="gemm", ahead=3, inline=False, kind="bulk"),
        "gemm1_inline": dict(mode="gemm", ahead=1, inline=True, kind="bulk"),
        "gemm1_load": dict(mode="gemm", ahead=1, inline=False, kind="load"),
    }
    graphs, outs = {}, {}
    for name, cfg in variants.items():
        CFG.update(cfg)
        try:
            for _ in range(2):
                a = patched_stage(handoff, noise)
            torch.cuda.synchronize()
            g = torch.cuda.CUDAGraph()
            with torch.cuda.graph(g):
                a = patched_stage(handoff, noise)
            g.replay()
            torch.cuda.synchronize()
            graphs[name], outs[name] = g, a
        except Exception as ex:  # keep going: report it
            print(f"variant {name} failed: {ex!r}"[:2000], flush=True)
    diffs = {k: (v.float() - outs["base"].float()).abs().max().item() for k, v in outs.items()}
    t = timed(graphs, 200, warm=20)
    out["pi0_action"] = {k: {**{m: round(x, 3) for m, x in v.items()}, "diff_vs_base": diffs[k]} for k, v in t.items()}
    with open(os.path.join(OUT, "l2pf.json"), "w") as f:
        json.dump(out, f, indent=1)
    print(f"\npi0 action stage, batch 1, chunk {CHUNK} B  ({out['gpu']})")
    print(f"{'variant':14s} {'p50 ms':>8s} {'p99 ms':>8s} {'diff':>6s}")
    for k, v in out["pi0_action"].items():
        print(f"{k:14s} {v['median']:8.3f} {v['p99']:8.3f} {v['diff_vs_base']:6.3f}")


if __name__ == "__main__":
    main()
