"""The action stages' folded norms, on the CPU reference paths: a GEMM on the un-normalised
rows with the norm weight folded into its weight, then each row scaled by the 1 / rms that
the split-K GEMM's row statistics give, equals the norm followed by the GEMM."""

import torch
from torch import nn

from shared.models.fused import RowStats, Workspace, gated_act, split_qkv
from shared.models.layers import RMSNorm, folded_norm_linear, folded_weight


def _stats(x: torch.Tensor, tiles: int) -> RowStats:
    """Per-tile row sums of squares of x [rows, width], laid out as the split-K GEMM writes them."""
    rows, width = x.shape
    return RowStats((x.float() ** 2).view(rows, tiles, width // tiles).sum(-1).t().contiguous(), width)


def _parts(width=64, out=96, seed=0):
    g = torch.Generator().manual_seed(seed)
    norm, lin = RMSNorm(width), nn.Linear(width, out, bias=False)
    with torch.no_grad():
        norm.weight.copy_(torch.rand(width, generator=g) + 0.5)
        lin.weight.copy_(torch.randn(out, width, generator=g) / width ** 0.5)
    x = torch.randn(2, 5, width, generator=g) * 3
    return norm, lin, x


@torch.no_grad()
def test_folded_qkv_equals_norm_then_gemm():
    n_q, n_kv, d = 4, 1, 16
    norm, lin, x = _parts(out=(n_q + 2 * n_kv) * d)
    ws = Workspace(torch.device("cpu"))
    ws.keep_stats(x, _stats(x.view(10, 64), tiles=4))
    raw, stats = folded_norm_linear(x, norm, lin, ws)
    assert stats is not None
    ang = torch.rand(2, 5, d // 2, generator=torch.Generator().manual_seed(3)) * 6
    cos, sin = ang.cos(), ang.sin()
    kv_fold, kv_ref = torch.zeros(2, 2, n_kv, 5, d), torch.zeros(2, 2, n_kv, 5, d)
    q_fold = split_qkv(raw, n_q, n_kv, d, kv_fold[0], kv_fold[1], cos, sin, row_stats=stats, row_eps=norm.eps)
    q_ref = split_qkv(lin(norm(x)), n_q, n_kv, d, kv_ref[0], kv_ref[1], cos, sin)
    torch.testing.assert_close(q_fold, q_ref, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(kv_fold, kv_ref, atol=1e-5, rtol=1e-5)


@torch.no_grad()
def test_folded_gated_mlp_input_equals_norm_then_gemm():
    norm, lin, x = _parts(out=2 * 48)
    ws = Workspace(torch.device("cpu"))
    ws.keep_stats(x, _stats(x.view(10, 64), tiles=2))
    raw, stats = folded_norm_linear(x, norm, lin, ws)
    for act in ("gelu_tanh", "silu"):
        torch.testing.assert_close(gated_act(raw, act, stats, norm.eps), gated_act(lin(norm(x)), act),
                                   atol=1e-5, rtol=1e-5)


@torch.no_grad()
def test_without_stats_the_norm_runs():
    norm, lin, x = _parts()
    ws = Workspace(torch.device("cpu"))
    ws.keep_stats(x, _stats(x.view(10, 64), tiles=4))
    # Another tensor object over the same memory (a view) is not the one the stats describe.
    out, stats = folded_norm_linear(x.view(2, 5, 64), norm, lin, ws)
    assert stats is None
    torch.testing.assert_close(out, lin(norm(x)))
    ws.keep_stats(x, None)
    assert ws.stats_of(x) is None
    lin_b = nn.Linear(64, 96, bias=True)  # a bias must not be scaled by 1 / rms: no folding
    ws.keep_stats(x, _stats(x.view(10, 64), tiles=4))
    assert folded_norm_linear(x, norm, lin_b, ws)[1] is None


def test_folded_weight_follows_weight_changes():
    norm, lin, _ = _parts()
    w1 = folded_weight(lin, norm)
    torch.testing.assert_close(w1, lin.weight * norm.weight[None, :])
    assert folded_weight(lin, norm) is w1  # made once
    with torch.no_grad():
        norm.weight.mul_(2)
    w2 = folded_weight(lin, norm)
    torch.testing.assert_close(w2, lin.weight * norm.weight[None, :])
    assert "_folded" not in lin.state_dict() and torch.equal(lin.state_dict()["weight"], lin.weight)
