"""Experiment: one persistent CUDA C++ kernel per action-expert layer-step (pi0's expert).

The kernel (cuda_layer.cu, beside this file) is built at run time by NVRTC for the layer's
dimensions and launched through the CUDA driver on PyTorch's current stream, so it is captured
into the action stage's CUDA graph like any other kernel. What it does that the Triton
persistent kernel (persistent_layer.py) cannot: every A operand is read once per unit into
shared memory, and a producer warp streams all of the CTA's weight chunks for the launch
through a ring of shared-memory slots with bulk copies on mbarriers, running ahead across the
grid barriers. The RMSNorm weights are folded into copies of the QKV and gate/up weights
(``folded_weights``) and 1/rms scales the GEMM output rows; the rows' sums of squares come from
the phase that wrote the tile (o for x1, down for the next layer's x).

    OUT=/tmp OUT_NAME=kernel_exp_cuda_layer_v2_h100.json ITERS=50 STAMPS=1 TRITON=1 \
        python bench/experiments/cuda_layer.py                                # check, timing, phases
    LAYER_ONLY=1 ncu -k regex:layer_step -c 1 --section SpeedOfLight --section WarpStateStats \
        python bench/experiments/cuda_layer.py                               # one launch under Nsight Compute

Prints a table last and writes the JSON under OUT. STAMPS=1 adds ``%globaltimer`` stamps per
CTA at each phase's loads-done and end, and inside the attention unit. TRITON=1 times the Triton
persistent kernel's record configuration in the same process as a third variant.

Result on an H100 (docs/RESULTS.md, model zoo, "The persistent CUDA C++ kernel, second
version"): correct (6.3e-3 relative to main over the whole stage, graph replay equal to eager),
47.8 us per layer-step against 62.8 for the first version; the action stage takes 9.19 ms
against main's 9.08 and the Triton persistent kernel's 7.53 at batch 1.
"""
from __future__ import annotations

import ctypes
import json
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from shared.models import build_model, fused, layers  # noqa: E402

from timing import alternating_ms, capture_checked, pct, route_expert_layers  # noqa: E402  (this folder)

OUT = os.environ.get("OUT", "/tmp")
SRC = os.path.join(os.path.dirname(os.path.abspath(__file__)), "cuda_layer.cu")
SMEM = 232448 - 1024  # the most an H100 CTA may opt into, less 1 KB of static shared memory
THREADS = 288  # 8 consumer warps + 1 producer warp


class _Params(ctypes.Structure):
    _fields_ = ([(n, ctypes.c_void_p) for n in (
        "x", "wqkv", "g1", "cos", "sin", "q", "k_out", "v_out", "k_all", "v_all", "bias", "apart", "aml", "attn",
        "wo", "part", "x1", "g2", "wgu", "h", "wd", "out", "cnt", "bar", "stamps", "ss_in", "ss_mid", "ss_out", "wqkv_next")]
        + [(n, ctypes.c_longlong) for n in (
            "cos_sb", "cos_ss", "k_sb", "k_ss", "v_sb", "v_ss", "ka_sb", "ka_ss", "va_sb", "va_ss", "b_sb", "b_sm")]
        + [("eps", ctypes.c_float), ("scale", ctypes.c_float)])


def _check(result, what: str):
    err = result[0]
    if int(err) != 0:
        raise RuntimeError(f"{what} failed: {err}")
    return result[1] if len(result) == 2 else result[1:]


_KERNELS: dict[tuple, object] = {}


def kernel_for(dims: dict[str, int]):
    """The layer_step function compiled for these dimensions (NVRTC, sm_90), cached."""
    from cuda.bindings import driver
    key = tuple(sorted(dims.items()))
    if key in _KERNELS:
        return _KERNELS[key]
    try:
        cubin = _nvrtc_cubin(dims)
    except Exception as exc:  # no NVRTC library: the toolkit's nvcc builds the same source
        print(f"NVRTC unavailable ({exc}); building with nvcc")
        cubin = _nvcc_cubin(dims)
    torch.cuda.init()
    torch.empty(1, device="cuda")  # the primary context is current on this thread
    mod = _check(driver.cuModuleLoadData(cubin), "cuModuleLoadData")
    fn = _check(driver.cuModuleGetFunction(mod, b"layer_step"), "cuModuleGetFunction")
    _check((driver.cuFuncSetAttribute(
        fn, driver.CUfunction_attribute.CU_FUNC_ATTRIBUTE_MAX_DYNAMIC_SHARED_SIZE_BYTES, SMEM)[0], None), "smem")
    regs = _check(driver.cuFuncGetAttribute(driver.CUfunction_attribute.CU_FUNC_ATTRIBUTE_NUM_REGS, fn), "regs")
    local = _check(driver.cuFuncGetAttribute(driver.CUfunction_attribute.CU_FUNC_ATTRIBUTE_LOCAL_SIZE_BYTES, fn), "lmem")
    print(f"layer_step {dims}: {regs} registers, {local} B local")
    _KERNELS[key] = (mod, fn)
    return _KERNELS[key]


def _arch() -> str:
    major, minor = torch.cuda.get_device_capability()
    return f"sm_{major}{minor}"


def _nvcc_cubin(dims: dict[str, int]) -> bytes:
    import subprocess
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "layer.cubin")
        subprocess.run(["nvcc", f"-arch={_arch()}", "-cubin", "-std=c++17", "--use_fast_math", "-lineinfo", "-o", out,
                        SRC] + [f"-D{k}={v}" for k, v in dims.items()], check=True)
        return open(out, "rb").read()


def _nvrtc_cubin(dims: dict[str, int]) -> bytes:
    from cuda.bindings import nvrtc
    src = open(SRC).read()
    prog = _check(nvrtc.nvrtcCreateProgram(src.encode(), b"cuda_layer.cu", 0, [], []), "nvrtcCreateProgram")
    opts = [f"--gpu-architecture={_arch()}".encode(), b"-std=c++17", b"-default-device", b"--use_fast_math",
            b"-lineinfo"] + [f"-D{k}={v}".encode() for k, v in dims.items()]
    t0 = time.perf_counter()
    err = nvrtc.nvrtcCompileProgram(prog, len(opts), opts)[0]
    size = _check(nvrtc.nvrtcGetProgramLogSize(prog), "log size")
    log = b" " * size
    nvrtc.nvrtcGetProgramLog(prog, log)
    if int(err) != 0:
        raise RuntimeError("NVRTC compile failed:\n" + log.decode(errors="replace"))
    if log.strip(b" \x00\n"):
        print(log.decode(errors="replace")[:4000])
    n = _check(nvrtc.nvrtcGetCUBINSize(prog), "cubin size")
    cubin = b" " * n
    _check((nvrtc.nvrtcGetCUBIN(prog, cubin)[0], None), "cubin")
    print(f"NVRTC built layer_step {dims} in {time.perf_counter() - t0:.1f} s")
    return cubin


class CudaState:
    """Per-stage-call scratch shared by the layer launches (they run in stream order)."""

    def __init__(self, device, stamps: bool):
        self.cnt = torch.zeros(64, dtype=torch.int32, device=device)
        self.bar = torch.zeros(2, dtype=torch.int32, device=device)
        self.buffers: dict[tuple, dict] = {}
        self.stamps = [] if stamps else None
        # Row sums of squares per 64-column tile, left by one launch's down phase for the next
        # layer's norm; valid only when that next layer follows on the same output.
        self.ss_x = torch.zeros(64 * 64, dtype=torch.float32, device=device)
        self.ss_mid = torch.zeros(64 * 64, dtype=torch.float32, device=device)
        self.prev: tuple | None = None  # (layer index, output pointer) of the last launch


def _ptr(t):
    return t.data_ptr()


def folded_weights(layer) -> tuple:
    """The QKV and gate/up weights with the RMSNorm weights multiplied into their columns
    (the kernel applies only 1 / rms, to the GEMM's output rows): main's copies
    (``layers.folded_weight``, made once per layer, 396 MB for pi0's expert), so the two paths
    of one process share them."""
    return (layers.folded_weight(layer.attn.qkv, layer.attn_norm),
            layers.folded_weight(layer.mlp.gate_up, layer.mlp_norm))


def layer_cuda(layer, x, k_out, v_out, rope, bias, k_all, v_all, st: CudaState):
    from cuda.bindings import driver
    b, s, w = x.shape
    at = layer.attn
    n_q, n_kv, d = at.n_heads, at.n_kv_heads, at.head_dim
    f = layer.mlp.down.weight.shape[1]
    m, length = b * s, k_all.shape[2]
    assert n_kv == 1 and d == 256 and m <= 64 and layer.mlp.act == "gelu_tanh" and bias is not None
    assert at.qkv.bias is None and at.q_norm is None and layer.mlp.down.bias is None and at.o.bias is None
    dims = dict(W_=w, F_=f, NQ=n_q, D=d, SEQ=s, BATCH=b, ROWS=m, KEYS=length)
    _, fn = kernel_for(dims)
    dev = x.device
    key = tuple(dims.values())
    if key not in st.buffers:
        r = s * n_q
        units2 = b * ((r + 63) // 64) * ((length + 47) // 48)
        st.buffers[key] = dict(
            q=torch.empty(m * n_q * d, device=dev, dtype=x.dtype),
            apart=torch.empty(units2 * 64 * d, device=dev, dtype=torch.float32),
            aml=torch.empty(units2 * 64 * 2, device=dev, dtype=torch.float32),
            attn=torch.empty(m * n_q * d, device=dev, dtype=x.dtype),
            part=torch.empty(max(w // 64 * (n_q * d // 256), w // 64 * (f // 512)) * 64 * 64, device=dev,
                             dtype=torch.float32),
            x1=torch.empty(m * w, device=dev, dtype=x.dtype), h=torch.empty(m * f, device=dev, dtype=x.dtype))
    buf = st.buffers[key]
    out = torch.empty(b, s, w, device=dev, dtype=x.dtype)
    xc = x.contiguous()
    cos, sin = rope
    stamps = None
    if st.stamps is not None:
        stamps = torch.zeros(256 * 16, dtype=torch.int64, device=dev)
        st.stamps.append(stamps)
    wqkv, wgu = folded_weights(layer)
    index = next((i for i, known in enumerate(LAYERS) if known is layer), -1)
    chained = index > 0 and st.prev == (index - 1, xc.data_ptr())
    assert w // 64 * 64 <= st.ss_x.numel()
    p = _Params(
        _ptr(xc), _ptr(wqkv), _ptr(layer.attn_norm.weight), _ptr(cos), _ptr(sin), _ptr(buf["q"]),
        _ptr(k_out), _ptr(v_out), _ptr(k_all), _ptr(v_all), _ptr(bias), _ptr(buf["apart"]), _ptr(buf["aml"]),
        _ptr(buf["attn"]), _ptr(at.o.weight), _ptr(buf["part"]), _ptr(buf["x1"]), _ptr(layer.mlp_norm.weight),
        _ptr(wgu), _ptr(buf["h"]), _ptr(layer.mlp.down.weight), _ptr(out), _ptr(st.cnt),
        _ptr(st.bar), stamps.data_ptr() if stamps is not None else 0,
        _ptr(st.ss_x) if chained else 0, _ptr(st.ss_mid), _ptr(st.ss_x),
        _ptr(folded_weights(LAYERS[(index + 1) % len(LAYERS)])[0]) if index >= 0 else 0,
        cos.stride(0) if cos.shape[0] > 1 else 0, cos.stride(1), k_out.stride(0), k_out.stride(2),
        v_out.stride(0), v_out.stride(2), k_all.stride(0), k_all.stride(2), v_all.stride(0), v_all.stride(2),
        bias.stride(0) if bias.shape[0] > 1 else 0, bias.stride(2) if bias.shape[2] > 1 else 0,
        layer.attn_norm.eps, d ** -0.5)
    assert cos.stride(2) == 1 and cos.dtype == torch.float32 and sin.stride() == cos.stride()
    assert k_out.stride(3) == 1 and k_all.stride(3) == 1 and bias.stride(3) == 1
    args = (ctypes.c_void_p * 1)(ctypes.addressof(p))
    grid = fused._sm_count(dev)
    stream = driver.CUstream(torch.cuda.current_stream(dev).cuda_stream)
    _check((driver.cuLaunchKernel(fn, grid, 1, 1, THREADS, 1, 1, SMEM, stream, ctypes.addressof(args), 0)[0], None),
           "cuLaunchKernel")
    st.prev = (index, out.data_ptr())
    return out


LAYERS: list = []  # the expert layers in order: a launch knows its predecessor and prefetches its successor


MODE = {"cuda": False, "stamps": False, "state": None}
route_expert_layers(MODE, "cuda", lambda device: CudaState(device, MODE["stamps"]), layer_cuda)


def check_layer(model, hand) -> dict:
    """One expert layer, CUDA against main's fused path, on the stage's own inputs (first step and later step)."""
    c = model.cfg
    layer = model.expert.layers[3]
    dev = hand["kv"].device
    res = {}
    g = torch.Generator(device="cpu").manual_seed(5)
    lp = hand["prefix_mask"].shape[1]
    total = lp + 1 + c.horizon
    for name, s, off in (("first_step", 1 + c.horizon, lp), ("later_step", c.horizon, lp + 1)):
        x = torch.randn(1, s, c.expert_width, generator=g).to(dev, torch.bfloat16)
        kv0 = torch.randn(1, 2, 1, total, c.head_dim, generator=g).to(dev, torch.bfloat16)
        allowed = torch.ones(1, s, total, dtype=torch.bool, device=dev)
        allowed[:, :, lp // 2: lp // 2 + 7] = False  # some masked prefix keys
        if s == 1 + c.horizon:
            allowed[:, 0, lp + 1:] = False
        bias = layers.attn_bias(allowed if s == 1 + c.horizon else allowed[:, :1], c.heads, torch.bfloat16)
        pos = torch.arange(off, off + s, device=dev)[None]
        rope = layers.rope_cos_sin(pos, c.head_dim)
        outs, kvs = [], []
        for use in (False, True):
            MODE["cuda"] = use
            kv = kv0.clone()
            ws = layers.Workspace(dev)
            y = layer.forward_fused(x, kv[:, 0, :, off:off + s], kv[:, 1, :, off:off + s], rope, bias, kv[:, 0], kv[:, 1], ws)
            torch.cuda.synchronize()
            outs.append(y.float())
            kvs.append(kv.float())
        MODE["cuda"] = False
        ref, got = outs
        res[name] = {"rel_err": float((got - ref).norm() / ref.norm()),
                     "max_abs": float((got - ref).abs().max()),
                     "kv_rel_err": float((kvs[1] - kvs[0]).norm() / kvs[0].norm()),
                     "finite": bool(torch.isfinite(got).all())}
    return res


STAMP_NAMES = ["start", "qkv_loaded", "qkv_end", "attn_loaded", "attn_end", "merge_end", "o_loaded", "o_end",
               "gu_loaded", "gu_mma", "gu_end", "down_loaded", "down_end"]
PHASE_ENDS = {"qkv": 2, "attention": 4, "merge": 5, "o": 7, "gate_up": 10, "down": 12}


def stamp_profile(stamps: list, grid: int) -> dict:
    """Per layer launch: each phase's end at its latest CTA (since the previous phase's latest end),
    and per sub-step the mean over the CTAs that stamped it (us, mean over launches)."""
    ts = torch.stack([t.view(256, 16)[:grid] for t in stamps]).double().cpu()
    start = ts[:, :, 0].min(1).values
    out = {}
    prev = torch.zeros_like(start)
    for name, idx in PHASE_ENDS.items():
        end = ts[:, :, idx].max(1).values - start
        out[name] = float((end - prev).mean() / 1e3)
        prev = end
    out["total"] = float(prev.mean() / 1e3)
    sub = {}
    for i in range(1, len(STAMP_NAMES)):
        a, b = ts[:, :, i - 1], ts[:, :, i]
        ok = (a > 0) & (b > 0)
        if ok.any():
            sub[f"{STAMP_NAMES[i - 1]}->{STAMP_NAMES[i]}"] = float(((b - a)[ok]).mean() / 1e3)
    out["sub_steps_mean_cta"] = sub
    attn = {}  # inside the attention unit: loads, QK^T, softmax, PV, stores
    marks = [("attn_loaded", 3), ("qk", 13), ("softmax", 14), ("pv", 15), ("attn_end", 4)]
    for (na, ia), (nb, ib) in zip(marks, marks[1:]):
        a, b = ts[:, :, ia], ts[:, :, ib]
        ok = (a > 0) & (b > 0)
        if ok.any():
            attn[f"{na}->{nb}"] = float(((b - a)[ok]).mean() / 1e3)
    out["attention_mean_cta"] = attn
    return out


def run(iters: int) -> dict:
    dev = torch.device("cuda")
    model = build_model("pi0", "full", device=dev, seed=0)
    LAYERS.extend(model.expert.layers)
    with torch.no_grad():  # random norm weights, so the norms on the shared tiles are exercised
        g = torch.Generator(device="cpu").manual_seed(7)
        for mod in model.modules():
            if isinstance(mod, layers.RMSNorm):
                mod.weight.copy_((1 + 0.3 * torch.randn(mod.weight.shape, generator=g)).to(mod.weight.dtype))
    gen = torch.Generator().manual_seed(1234)
    images, state, tokens = model.example_inputs(1, device=dev, generator=gen)
    tokens[:, model.io.prompt_len // 2:] = 0
    noise = model.noise(1, device=dev, generator=gen).to(torch.bfloat16)
    res = {"gpu": torch.cuda.get_device_name(), "torch": torch.__version__, "commit": os.environ.get("ROBION_COMMIT")}
    with torch.inference_mode():
        hand = model.vlm_stage(images, state, tokens)
        hand = {k: v.clone() for k, v in hand.items()}
        res["layer_check"] = check_layer(model, hand)
        print("layer check:", json.dumps(res["layer_check"]))
        if os.environ.get("LAYER_ONLY"):  # e.g. under ncu: the two layer launches of the check only
            return res
        graphs, outs = {}, {}
        pool = torch.cuda.graph_pool_handle()
        variants = [("main", False), ("cuda", True)]
        triton_mode = None
        if os.environ.get("TRITON"):  # the Triton persistent kernel's record, in the same process
            import persistent_layer  # its layer hook wraps this one's: off, it passes on to ours
            persistent_layer.CFG.update(dict(persistent_layer.RECORD, timing=False))
            triton_mode = persistent_layer.MODE
            variants.append(("triton", False))
        for name, use in variants:
            MODE["cuda"] = use
            MODE["stamps"] = False
            if triton_mode is not None:
                triton_mode["persistent"] = name == "triton"
            graphs[name], *outs[name] = capture_checked(lambda: model.action_stage(hand, noise), pool)
        MODE["cuda"] = False
        if triton_mode is not None:
            triton_mode["persistent"] = False
        times = alternating_ms(graphs, iters)
        main_out = outs["main"][1]
        for n in graphs:
            eager, graphed = outs[n]
            res[n] = {"p50_ms": statistics.median(times[n]), "p99_ms": pct(times[n], 0.99),
                      "rel_err_vs_main": float((graphed - main_out).norm() / main_out.norm()),
                      "graph_vs_eager_max_abs": float((graphed - eager).abs().max()),
                      "finite": bool(torch.isfinite(graphed).all())}
        if os.environ.get("STAMPS"):
            MODE["cuda"] = MODE["stamps"] = True
            ws_state = []
            for _ in range(3):
                model.action_stage(hand, noise)
                torch.cuda.synchronize()
                ws_state.append(MODE["state"])
            MODE["cuda"] = MODE["stamps"] = False
            st = ws_state[-1]
            res["phases_us"] = stamp_profile(st.stamps, fused._sm_count(dev))
    return res


def main():
    iters = int(os.environ.get("ITERS", "50"))
    res = run(iters)
    if "main" not in res:
        return
    path = os.path.join(OUT, os.environ.get("OUT_NAME", "kernel_exp_cuda_layer_h100.json"))
    with open(path, "w") as fh:
        json.dump(res, fh, indent=1)
    print(f"\npi0 action stage, batch 1, {iters} replays each, alternating ({res['gpu']})")
    print(f"{'variant':8s} {'p50 ms':>8s} {'p99 ms':>8s} {'rel err vs main':>16s} {'graph-eager':>12s}")
    for n in [v for v in ("main", "cuda", "triton") if v in res]:
        r = res[n]
        print(f"{n:8s} {r['p50_ms']:8.3f} {r['p99_ms']:8.3f} {r['rel_err_vs_main']:16.2e} {r['graph_vs_eager_max_abs']:12.2e}")
    if "phases_us" in res:
        ph = res["phases_us"]
        print("phases (us per layer-step, latest CTA):",
              {k: round(v, 2) for k, v in ph.items() if not isinstance(v, dict)})
        print("sub-steps (us, mean CTA):", {k: round(v, 2) for k, v in ph["sub_steps_mean_cta"].items()})
        print("attention unit (us, mean CTA):", {k: round(v, 2) for k, v in ph["attention_mean_cta"].items()})


if __name__ == "__main__":
    main()
