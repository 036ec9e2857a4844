"""Probe: which SDPA backend is fastest for the zoo's attention shapes (bf16, CUDA graphs)."""
import sys
import torch
import torch.nn.functional as F
from torch.nn.attention import SDPBackend, sdpa_kernel

SHAPES = {  # name: (b, n_kv, s*g, L, d, mask_rows)
    "pi0_act": (1, 1, 400, 611, 256, 1), "pi0_act_b4": (4, 1, 400, 611, 256, 1), "pi0_step0": (1, 1, 408, 611, 256, 408),
    "pi0_vlm": (1, 1, 4480, 560, 256, 1), "smol_joint": (1, 5, 150, 227, 64, 150), "xr0_dit": (1, 8, 32, 208, 128, 32),
    "groot_cross": (1, 32, 49, 560, 48, 1), "vit": (2, 16, 256, 256, 72, 0),
}


def timeit(fn, n=20):
    s = torch.cuda.Stream()
    s.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(s):
        fn()
    torch.cuda.current_stream().wait_stream(s)
    g = torch.cuda.CUDAGraph()
    with torch.cuda.graph(g):
        for _ in range(n):
            fn()
    for _ in range(3):
        g.replay()
    e0, e1 = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    e0.record()
    for _ in range(10):
        g.replay()
    e1.record()
    torch.cuda.synchronize()
    return e0.elapsed_time(e1) / (10 * n) * 1000


for name, (b, h, m, L, d, rows) in SHAPES.items():
    q = torch.randn(b, m, h, d, device="cuda", dtype=torch.bfloat16).transpose(1, 2)
    kv = torch.randn(b, 3, 2, h, L + 5, d, device="cuda", dtype=torch.bfloat16)
    k, v = kv[:, 1, 0, :, :L], kv[:, 1, 1, :, :L]
    mask = None
    if rows:
        st = torch.zeros(b, 1, rows, (L + 15) // 16 * 16, device="cuda", dtype=torch.bfloat16)
        mask = st[..., :L]
        mask[..., -7:] = -1e30
    res = []
    for be in ["EFFICIENT_ATTENTION", "CUDNN_ATTENTION", "FLASH_ATTENTION", "MATH"]:
        try:
            with sdpa_kernel([getattr(SDPBackend, be)]):
                us = timeit(lambda: F.scaled_dot_product_attention(q, k, v, attn_mask=None if be == "FLASH_ATTENTION" else mask))
            res.append(f"{be[:5]} {us:7.1f}us")
        except Exception as e:
            res.append(f"{be[:5]} n/a({type(e).__name__})")
    print(f"{name:<12}", " | ".join(res), flush=True)
