"""GPU checks of the model zoo (run on a GPU host: ``pytest -m gpu tests/gpu``)."""

import pytest
import torch

from shared.models import build_model
from shared.models import fused

pytestmark = pytest.mark.gpu
ARCHS = ["pi0", "smolvla", "groot_n15", "xr0"]
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def _both_paths(fn):
    old = fused.set_triton(True)
    try:
        fast = fn()
        fused.set_triton(False)
        ref = fn()
    finally:
        fused.set_triton(old)
    return fast, ref


@needs_cuda
@pytest.mark.parametrize("n_q,n_kv,d,rope,qk_norm", [(8, 1, 256, True, False), (15, 5, 64, True, False),
                                                     (16, 8, 128, True, True), (8, 8, 128, True, True),
                                                     (16, 16, 72, False, False), (15, 0, 64, True, False)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_split_qkv_matches_reference(n_q, n_kv, d, rope, qk_norm, dtype):
    g = torch.Generator(device="cuda").manual_seed(0)
    b, s, extra = 2, 7, 5
    qkv = torch.randn(b, s, (n_q + 2 * n_kv) * d, device="cuda", generator=g).to(dtype)
    cos = sin = qn = kn = None
    if rope:
        ang = torch.rand(b, s, d // 2, device="cuda", generator=g) * 6
        cos, sin = ang.cos(), ang.sin()
    if qk_norm:
        qn, kn = torch.rand(d, device="cuda", generator=g).to(dtype), torch.rand(d, device="cuda", generator=g).to(dtype)

    def run():
        cache = torch.zeros(b, 3, 2, max(n_kv, 1), s + extra, d, device="cuda", dtype=dtype)  # strided KV views
        k_out, v_out = (cache[:, 1, 0, :, extra:], cache[:, 1, 1, :, extra:]) if n_kv else (None, None)
        q = fused.split_qkv(qkv, n_q, n_kv, d, k_out, v_out, cos, sin, qn, kn)
        return q, cache

    (q1, c1), (q2, c2) = _both_paths(run)
    tol = dict(atol=2e-2, rtol=2e-2) if dtype == torch.bfloat16 else dict(atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(q1, q2, **tol)
    torch.testing.assert_close(c1, c2, **tol)


@needs_cuda
@pytest.mark.parametrize("act", ["gelu_tanh", "silu"])
def test_gated_act_matches_reference(act):
    x = torch.randn(3, 50, 2 * 4096, device="cuda", dtype=torch.bfloat16)
    fast, ref = _both_paths(lambda: fused.gated_act(x, act))
    torch.testing.assert_close(fast, ref, atol=2e-2, rtol=2e-2)


def _row_stats(rows: int, width: int, tiles: int, seed: int) -> fused.RowStats:
    g = torch.Generator(device="cuda").manual_seed(seed)
    ss = torch.rand(tiles, rows, device="cuda", generator=g) * width * 4 / tiles
    return fused.RowStats(ss, width)


@needs_cuda
@pytest.mark.parametrize("act", ["gelu_tanh", "silu"])
@pytest.mark.parametrize("rows,f,tiles", [(51, 4096, 32), (100, 2048, 23)])
def test_gated_act_row_stats_matches_reference(act, rows, f, tiles):
    x = torch.randn(rows, 2 * f, device="cuda", dtype=torch.bfloat16) * 4
    stats = _row_stats(rows, 1024, tiles, rows)
    fast, ref = _both_paths(lambda: fused.gated_act(x, act, stats, 1e-6))
    assert _rel(fast, ref) < 1e-2
    scaled = x.double() * stats.rstd(1e-6).double()[:, None]  # act(r g) * (r u), in float64
    gate, up = scaled.chunk(2, dim=-1)
    gate = torch.nn.functional.gelu(gate, approximate="tanh") if act == "gelu_tanh" else torch.nn.functional.silu(gate)
    assert _rel(fast, gate * up) < 1e-2


@needs_cuda
@pytest.mark.parametrize("n_q,n_kv,d,tiles", [(8, 1, 256, 32), (15, 5, 64, 23), (15, 0, 64, 23)])
def test_split_qkv_row_stats_matches_reference(n_q, n_kv, d, tiles):
    g = torch.Generator(device="cuda").manual_seed(d)
    b, s = 2, 25
    qkv = (torch.randn(b, s, (n_q + 2 * n_kv) * d, device="cuda", generator=g) * 4).bfloat16()
    ang = torch.rand(b, s, d // 2, device="cuda", generator=g) * 6
    cos, sin = ang.cos(), ang.sin()
    stats = _row_stats(b * s, 720, tiles, d)

    def run():
        cache = torch.zeros(b, 2, max(n_kv, 1), s, d, device="cuda", dtype=torch.bfloat16)
        k_out, v_out = (cache[:, 0], cache[:, 1]) if n_kv else (None, None)
        return fused.split_qkv(qkv, n_q, n_kv, d, k_out, v_out, cos, sin, row_stats=stats, row_eps=1e-6), cache

    (q1, c1), (q2, c2) = _both_paths(run)
    assert _rel(q1, q2) < 1e-2
    if n_kv:
        assert _rel(c1, c2) < 1e-2
    # Scaling the rows first and splitting without statistics gives the same heads.
    scaled = (qkv.float() * stats.rstd(1e-6).view(b, s, 1)).bfloat16()
    q3 = fused.split_qkv(scaled, n_q, n_kv, d, torch.zeros_like(c1[:, 0]) if n_kv else None,
                         torch.zeros_like(c1[:, 1]) if n_kv else None, cos, sin)
    assert _rel(q1, q3) < 1e-2


@needs_cuda
@pytest.mark.parametrize("grid,size,c,dtype", [(48, 16, 1152, torch.bfloat16), (48, 24, 64, torch.float32),
                                               (7, 10, 33, torch.float32), (9, 4, 2000, torch.bfloat16)])
def test_resize_table_matches_interpolate(grid, size, c, dtype):
    g = torch.Generator(device="cuda").manual_seed(0)
    table = torch.randn(grid * grid, c, device="cuda", generator=g).to(dtype)
    fast, ref = _both_paths(lambda: fused.resize_table(table, grid, size))
    assert fast.shape == (size * size, c)
    tol = dict(atol=1e-2, rtol=1e-2) if dtype == torch.bfloat16 else dict(atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(fast, ref, **tol)


@needs_cuda
@pytest.mark.parametrize("arch", ARCHS)
def test_tiny_fp32_triton_matches_reference(arch):
    m = build_model(arch, "tiny", seed=0, device="cuda", dtype=torch.float32)
    images, state, tokens = m.example_inputs(3, generator=torch.Generator().manual_seed(0))
    tokens[1, 3:] = 0
    noise = m.noise(3, generator=torch.Generator().manual_seed(1))
    with torch.inference_mode():
        fast, ref = _both_paths(lambda: m.action_stage(m.vlm_stage(images, state, tokens), noise))
    torch.testing.assert_close(fast, ref, atol=1e-4, rtol=1e-4)


@needs_cuda
@pytest.mark.parametrize("arch", ARCHS)
def test_full_models_in_bf16_follow_the_interface_an_executor_checks(arch):
    """The check every executor runs before serving a model: at full size in bf16 on the GPU, each handoff tensor is
    what handoff_spec (answered without running anything) says, and the actions are [B, horizon, action_dim]."""
    from shared.models.base import check_interface

    torch.cuda.empty_cache()
    check_interface(build_model(arch, "full", seed=0, device="cuda"), batches=(1, 2, 4))


@needs_cuda
@pytest.mark.parametrize("arch", ARCHS)
def test_full_graph_replay_equals_eager(arch):
    torch.cuda.empty_cache()
    m = build_model(arch, "full", seed=0, device="cuda")
    b = 2
    images, state, tokens = m.example_inputs(b, generator=torch.Generator().manual_seed(0))
    tokens[0, 10:] = 0
    noise = m.noise(b, generator=torch.Generator().manual_seed(1)).bfloat16()
    with torch.inference_mode():
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(2):
                eager_h = m.vlm_stage(images, state, tokens)
                eager = m.action_stage(eager_h, noise)
        torch.cuda.current_stream().wait_stream(side)
        spec = m.handoff_spec(b)
        assert {k: (tuple(v.shape), v.dtype) for k, v in eager_h.items()} == spec
        g1, g2 = torch.cuda.CUDAGraph(), torch.cuda.CUDAGraph()
        with torch.cuda.graph(g1):
            h = m.vlm_stage(images, state, tokens)
        with torch.cuda.graph(g2):
            out = m.action_stage(h, noise)
        images.copy_(torch.flip(images, dims=[2]))  # graphs must read the static inputs anew
        g1.replay()
        g2.replay()
        eager2 = m.action_stage(m.vlm_stage(images, state, tokens), noise)
        torch.cuda.synchronize()
    assert torch.isfinite(out).all()
    assert not torch.equal(eager, eager2)
    torch.testing.assert_close(out.float(), eager2.float(), atol=1e-2, rtol=1e-2)
    del m, g1, g2
    torch.cuda.empty_cache()


def _attn_inputs(b, h, m, length, d, rows, seed=0):
    """q ``[B, H, M, D]`` (strided), k/v as strided views into a KV cache, and a random additive
    mask over ``rows`` query rows (1: one row for all; 0: no mask)."""
    from shared.models.layers import attn_bias

    g = torch.Generator(device="cuda").manual_seed(seed)
    q = torch.randn(b, m, h, d, device="cuda", generator=g).bfloat16().transpose(1, 2)
    kv = torch.randn(b, 2, 2, h, length + 3, d, device="cuda", generator=g).bfloat16()
    k, v = kv[:, 1, 0, :, :length], kv[:, 1, 1, :, :length]
    bias = None
    if rows:
        allowed = torch.rand(b, rows, length, device="cuda", generator=g) > 0.3
        allowed[..., 0] = True
        bias = attn_bias(allowed, 1, torch.bfloat16)
    return q, k, v, bias


@needs_cuda
@pytest.mark.parametrize("b,h,m,length,d,rows", [(1, 1, 400, 611, 256, 1), (2, 1, 408, 611, 256, 408),
                                                 (2, 5, 150, 227, 64, 150), (3, 8, 32, 208, 128, 32),
                                                 (1, 4, 20, 33, 64, 0)])
def test_small_attention_matches_sdpa(b, h, m, length, d, rows):
    import torch.nn.functional as F

    q, k, v, bias = _attn_inputs(b, h, m, length, d, rows)
    out = fused.small_attention(q, k, v, bias)
    ref = F.scaled_dot_product_attention(q.float(), k.float(), v.float(), attn_mask=None if bias is None else bias.float())
    torch.testing.assert_close(out.float(), ref, atol=2e-2, rtol=2e-2)


@needs_cuda
@pytest.mark.parametrize("b,h,m,length,d,rows", [(1, 1, 4480, 560, 256, 1), (2, 1, 4480, 560, 256, 0),
                                                 (1, 2, 1500, 333, 128, 1500), (2, 1, 1100, 17, 64, 1)])
def test_gemm_attention_matches_float64(b, h, m, length, d, rows):
    q, k, v, bias = _attn_inputs(b, h, m, length, d, rows, seed=1)
    out = fused.gemm_attention(q, k, v, bias)
    s = q.double() @ k.double().transpose(-1, -2) / d ** 0.5
    ref = torch.softmax(s if bias is None else s + bias.double(), -1) @ v.double()
    assert out.shape == (b, h, m, d) and out.dtype == torch.bfloat16
    assert _rel(out, ref) < 5e-3
    # The flash kernel SDPA picks, on the same inputs, is no closer to float64.
    import torch.nn.functional as F
    lib = F.scaled_dot_product_attention(q, k, v, attn_mask=bias)
    assert _rel(out, ref) < 2 * _rel(lib, ref) + 1e-3


@needs_cuda
def test_gemm_attention_routing():
    """The VLM prefix of pi0 (one KV head, 4480 folded rows) takes the GEMM form; few rows
    (action stages), many KV heads, or long key sequences do not."""
    q = torch.empty(1, 560, 8, 256, device="cuda", dtype=torch.bfloat16)
    assert fused.gemm_attention_fits(q, 4480, 560, 256, 1)
    assert fused.gemm_attention_fits(q, 4480, 560, 256, 4)
    assert not fused.gemm_attention_fits(q, 408, 611, 256, 1)  # the Triton split-KV kernel's
    assert not fused.gemm_attention_fits(q, 4480, 560, 256, 8)
    assert not fused.gemm_attention_fits(q, 4480, 4096, 256, 1)
    assert not fused.gemm_attention_fits(q.float(), 4480, 560, 256, 1)


# --------------------------------------------------------------------------- fused skinny GEMMs


def _rel(a, b):
    return ((a.float() - b.float()).norm() / b.float().norm()).item()


def _ref(fn):
    old = fused.set_triton(False)
    try:
        return fn()
    finally:
        fused.set_triton(old)


@needs_cuda
@pytest.mark.parametrize("rows", [1, 50, 51, 102, 204, 300])
@pytest.mark.parametrize("k,n", [(1024, 32), (720, 96), (2048, 2560)])
def test_norm_linear_matches_reference(rows, k, n):
    g = torch.Generator(device="cuda").manual_seed(rows + k)
    x = torch.randn(rows, k, device="cuda", generator=g).bfloat16()
    nw = (torch.rand(k, device="cuda", generator=g) + 0.5).bfloat16()
    w = (torch.randn(n, k, device="cuda", generator=g) / k ** 0.5).bfloat16()
    bias = torch.randn(n, device="cuda", generator=g).bfloat16()
    for norm in (nw, None):
        fast = fused.norm_linear(x, norm, 1e-6, w, bias)
        ref = fused._norm_linear_ref(x.double(), None if norm is None else norm.double(), 1e-6, w.double(),
                                     bias.double())
        assert _rel(fast, ref) < 1e-2


@needs_cuda
@pytest.mark.parametrize("rows", [51, 102, 204])
@pytest.mark.parametrize("k,f,act", [(1024, 4096, "gelu_tanh"), (720, 2048, "silu")])
def test_norm_gated_mlp_in_matches_reference(rows, k, f, act):
    g = torch.Generator(device="cuda").manual_seed(rows)
    x = torch.randn(1, rows, k, device="cuda", generator=g).bfloat16()
    nw = (torch.rand(k, device="cuda", generator=g) + 0.5).bfloat16()
    w = (torch.randn(2 * f, k, device="cuda", generator=g) / k ** 0.5).bfloat16()
    out = torch.full((1, rows, f), float("nan"), device="cuda", dtype=torch.bfloat16)
    out.copy_(fused.norm_gated_mlp_in(x, nw, 1e-6, w, act))
    ref = fused._gated_act_ref(fused._norm_linear_ref(x.double(), nw.double(), 1e-6, w.double(), None), act)
    assert torch.isfinite(out).all() and _rel(out, ref) < 1e-2


@needs_cuda
@pytest.mark.parametrize("b,s,n_q,n_kv,d,k", [(1, 51, 8, 1, 256, 1024), (2, 50, 8, 1, 256, 1024),
                                              (1, 50, 15, 5, 64, 720), (4, 50, 15, 5, 64, 720),
                                              (2, 50, 15, 0, 64, 720)])
def test_norm_qkv_matches_reference(b, s, n_q, n_kv, d, k):
    g = torch.Generator(device="cuda").manual_seed(s + n_q)
    x = torch.randn(b, s, k, device="cuda", generator=g).bfloat16()
    nw = (torch.rand(k, device="cuda", generator=g) + 0.5).bfloat16()
    w = (torch.randn((n_q + 2 * n_kv) * d, k, device="cuda", generator=g) / k ** 0.5).bfloat16()
    ang = torch.rand(b, s, d // 2, device="cuda", generator=g) * 6
    cos, sin = ang.cos(), ang.sin()
    extra = 7

    def run(dtype, xx, nn, ww):
        cache = torch.full((b, 2, 2, max(n_kv, 1), s + extra, d), float("nan"), device="cuda", dtype=dtype)
        cache[..., :extra, :] = 0
        k_out, v_out = (cache[:, 1, 0, :, extra:], cache[:, 1, 1, :, extra:]) if n_kv else (None, None)
        q = fused.norm_qkv(xx, nn, 1e-6, ww, n_q, n_kv, d, k_out, v_out, cos, sin)
        return q, cache[:, 1]

    q1, c1 = run(torch.bfloat16, x, nw, w)
    q2, c2 = _ref(lambda: run(torch.float64, x.double(), nw.double(), w.double()))
    assert _rel(q1, q2) < 1e-2
    if n_kv:
        assert torch.isfinite(c1).all() and _rel(c1, c2) < 1e-2


@needs_cuda
@pytest.mark.parametrize("rows", [1, 51, 102, 204, 300])
@pytest.mark.parametrize("k,n", [(2048, 1024), (4096, 1024), (960, 720), (2048, 720), (64, 48)])
def test_linear_residual_splitk_matches_reference(rows, k, n):
    g = torch.Generator(device="cuda").manual_seed(rows * 7 + k)
    x = torch.randn(rows, k, device="cuda", generator=g).bfloat16()
    w = (torch.randn(n, k, device="cuda", generator=g) / k ** 0.5).bfloat16()
    r = torch.randn(rows, n, device="cuda", generator=g).bfloat16()
    bias = torch.randn(n, device="cuda", generator=g).bfloat16()
    ws = fused.Workspace(torch.device("cuda"))
    ref = torch.addmm(r.double(), x.double(), w.double().t()) + bias.double()
    # A fresh residual per call: the cuBLAS path (over 64 rows with small weights) may accumulate into it.
    outs = [fused.linear_residual_splitk(x, w, bias, r.clone(), ws) for _ in range(3)]
    assert _rel(outs[0], ref) < 1e-2
    assert all(torch.equal(o, outs[0]) for o in outs)  # fixed reduction order: deterministic
    assert int(ws._cnt.abs().sum()) == 0  # counters left at zero
    # With row statistics: the same product, and per-tile sums of squares of the stored values.
    out = fused.linear_residual_splitk(x, w, bias, r.clone(), ws, stats=True)
    assert _rel(out, ref) < 1e-2 and int(ws._cnt.abs().sum()) == 0
    stats = ws.stats_of(out)
    if rows <= fused.GEMM_CFG["max_rows"]:  # the Triton path takes every size when statistics are wanted
        assert stats is not None and stats.width == n and stats.ss.shape[1] == rows
        torch.testing.assert_close(stats.ss.sum(0), (out.double() ** 2).sum(1).float(), rtol=1e-5, atol=1e-3)
    else:  # cuBLAS path: no statistics, the norm after it runs as before
        assert stats is None
    assert ws.stats_of(outs[0]) is None


@needs_cuda
@pytest.mark.parametrize("b,h,m,length,d,rows", [(1, 1, 408, 611, 256, 408), (2, 1, 400, 611, 256, 1),
                                                 (2, 5, 150, 227, 64, 150), (1, 5, 150, 177, 64, 1)])
def test_small_attention_fused_combine(b, h, m, length, d, rows):
    import torch.nn.functional as F
    from shared.models.layers import attn_bias

    g = torch.Generator(device="cuda").manual_seed(m + length)
    q = torch.randn(b, m, h, d, device="cuda", generator=g).bfloat16().transpose(1, 2)
    kv = torch.randn(b, 2, 2, h, length + 3, d, device="cuda", generator=g).bfloat16()
    k, v = kv[:, 1, 0, :, :length], kv[:, 1, 1, :, :length]
    allowed = torch.rand(b, max(rows, 1), length, device="cuda", generator=g) > 0.3
    allowed[..., 0] = True
    bias = attn_bias(allowed, 1, torch.bfloat16)
    ws = fused.Workspace(torch.device("cuda"))
    out = fused.small_attention(q, k, v, bias, ws)
    ref = F.scaled_dot_product_attention(q.double(), k.double(), v.double(), attn_mask=bias.double())
    assert _rel(out, ref) < 1e-2
    assert torch.equal(out, fused.small_attention(q, k, v, bias, ws))
    assert int(ws._cnt.abs().sum()) == 0


@needs_cuda
@pytest.mark.parametrize("b", [1, 2])
def test_groot_action_stage_splitk_matches_reference(b):
    """GR00T's DiT with its o / fc2 projections on the split-K GEMM (bias and residual in the
    epilogue) against the plain PyTorch ops, full size, bf16."""
    torch.cuda.empty_cache()
    m = build_model("groot_n15", "full", seed=0, device="cuda")
    images, state, tokens = m.example_inputs(b, generator=torch.Generator().manual_seed(0))
    noise = m.noise(b, generator=torch.Generator().manual_seed(1)).bfloat16()
    with torch.inference_mode():
        h = m.vlm_stage(images, state, tokens)
        fast, ref = _both_paths(lambda: m.action_stage(h, noise))
    assert torch.isfinite(fast).all()
    if b == 1:
        assert not torch.equal(fast, ref)  # the split-K path did run (batch 2, 98 rows, stays on cuBLAS)
    assert _rel(fast, ref) < 2e-2, _rel(fast, ref)
    del m
    torch.cuda.empty_cache()


@needs_cuda
@pytest.mark.parametrize("arch", ["pi0", "smolvla"])
@pytest.mark.parametrize("b", [1, 2])
def test_full_action_stage_fused_matches_reference(arch, b):
    """The whole action stage on the fused kernels vs the plain PyTorch ops, full size, bf16,
    with random (non-identity) norm weights so that the norm folding is exercised."""
    torch.cuda.empty_cache()
    m = build_model(arch, "full", seed=0, device="cuda")
    g = torch.Generator(device="cuda").manual_seed(5)
    with torch.no_grad():
        for name, p in m.expert.named_parameters():
            if "norm" in name:
                p.copy_(torch.rand(p.shape, device="cuda", generator=g) + 0.5)
    images, state, tokens = m.example_inputs(b, generator=torch.Generator().manual_seed(0))
    tokens[0, 10:] = 0
    noise = m.noise(b, generator=torch.Generator().manual_seed(1)).bfloat16()
    with torch.inference_mode():
        h = m.vlm_stage(images, state, tokens)
        fast, ref = _both_paths(lambda: m.action_stage(h, noise))
    assert torch.isfinite(fast).all()
    assert _rel(fast, ref) < 2e-2, _rel(fast, ref)
    # The split-K GEMM's row statistics replaced the MLP norm, so the gate/up weight was folded.
    assert "_folded" in m.expert.layers[1].mlp.gate_up.__dict__
    del m
    torch.cuda.empty_cache()


@needs_cuda
def test_kernels_take_views_whose_last_dim_is_strided():
    """The Triton kernels index the last dim as contiguous. A transposed view (a user model's weight.t(), a
    permuted activation) used to be read as if it were laid out row-major: now it is made contiguous first."""
    import torch.nn.functional as F

    g = torch.Generator(device="cuda").manual_seed(5)
    # split-K residual GEMM: weight given as the transpose of a [k, n] tensor, x and the residual as column views.
    rows, k, n = 51, 1024, 2048
    w = (torch.randn(k, n, device="cuda", generator=g) / k ** 0.5).bfloat16().t()
    x = torch.randn(k, rows, device="cuda", generator=g).bfloat16().t()
    r = torch.randn(n, rows, device="cuda", generator=g).bfloat16().t()
    assert w.stride(-1) != 1 and x.stride(-1) != 1 and r.stride(-1) != 1
    ref = torch.addmm(r.double(), x.double(), w.double().t())
    ws = fused.Workspace(torch.device("cuda"))
    assert _rel(fused.linear_residual_splitk(x, w, None, r.clone(), ws), ref) < 1e-2
    # gated activation of a column view.
    a = torch.randn(2 * 4096, 50, device="cuda", generator=g).bfloat16().t()
    gate, up = a.double().chunk(2, dim=-1)
    assert _rel(fused.gated_act(a, "silu"), F.silu(gate) * up) < 1e-2
    # attention with q, k and v whose head dim is strided.
    b, h, m, length, d = 1, 1, 51, 611, 256
    q = torch.randn(b, h, d, m, device="cuda", generator=g).bfloat16().transpose(-1, -2)
    kk = torch.randn(b, h, d, length, device="cuda", generator=g).bfloat16().transpose(-1, -2)
    vv = torch.randn(b, h, d, length, device="cuda", generator=g).bfloat16().transpose(-1, -2)
    ref = F.scaled_dot_product_attention(q.double(), kk.double(), vv.double())
    assert _rel(fused.small_attention(q, kk, vv, None), ref) < 1e-2
    assert _rel(fused.small_attention(q, kk, vv, None, fused.Workspace(torch.device("cuda"))), ref) < 1e-2
    # The norm-folded GEMMs (bench experiments): a transposed weight and activation (norm_w None: no norm).
    k, n = 1024, 2048
    x = torch.randn(k, rows, device="cuda", generator=g).bfloat16().t()
    w = (torch.randn(k, n, device="cuda", generator=g) / k ** 0.5).bfloat16().t()
    ref = x.double() @ w.double().t()
    assert _rel(fused.norm_linear(x, None, 1e-6, w), ref) < 1e-2
    gate, up = ref.chunk(2, dim=-1)
    assert _rel(fused.norm_gated_mlp_in(x, None, 1e-6, w, "silu"), F.silu(gate) * up) < 1e-2
