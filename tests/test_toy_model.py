import torch

from shared.models import build_model


def test_toy_stages_shapes_and_determinism():
    m = build_model("toy", seed=3)
    images, state, tokens = m.example_inputs(2, generator=torch.Generator().manual_seed(0))
    noise = m.noise(2, generator=torch.Generator().manual_seed(1))
    a = m.action_stage(m.vlm_stage(images, state, tokens), noise)
    assert a.shape == (2, m.io.horizon, m.io.action_dim)
    b = build_model("toy", seed=3).action_stage(build_model("toy", seed=3).vlm_stage(images, state, tokens), noise)
    torch.testing.assert_close(a, b)
    c = build_model("toy", seed=4)
    assert not torch.allclose(a, c.action_stage(c.vlm_stage(images, state, tokens), noise))
