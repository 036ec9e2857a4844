"""The model zoo on the CPU: tiny configs for behaviour, full configs on the meta device for sizes."""

import dataclasses
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from shared.config import ConfigError, config_from_dict
from shared.models import ModelIO, VLAModel, build_model, get_architecture, register
from shared.models.registry import _ARCHS, build_meta
from shared.models.weights import load_weights, save_weights
from shared.placement import model_bytes

ARCHS = ["pi0", "smolvla", "groot_n15", "xr0"]

# Per-stage parameter counts of the published models (VLM, action stage).
SPEC = {"pi0": (2.92e9, 315e6), "smolvla": (303e6, 100e6), "groot_n15": (1.33e9, 1.07e9), "xr0": (4.44e9, 0.28e9)}


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    # Tiny models are launch-bound; extra threads only contend on a 2-core CI box.
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def run(m, images, state, tokens, noise):
    with torch.no_grad():
        return m.action_stage(m.vlm_stage(images, state, tokens), noise)


def inputs(m, b, seed=0):
    g = torch.Generator().manual_seed(seed)
    images, state, tokens = m.example_inputs(b, generator=g)
    for i in range(b):  # different prompt lengths per sample exercise the padding masks
        tokens[i, max(1, m.io.prompt_len - 2 * i - 1):] = 0
    return images, state, tokens, m.noise(b, generator=g)


@pytest.mark.parametrize("arch", ARCHS)
def test_full_parameter_counts_match_spec(arch):
    counts = build_meta(arch, "full").stage_parameters()
    vlm, act = SPEC[arch]
    assert abs(counts["vlm_params"] / vlm - 1) < 0.02, counts
    assert abs(counts["action_params"] / act - 1) < 0.02, counts


@pytest.mark.parametrize("arch", ARCHS)
def test_full_io_is_two_cameras(arch):
    m = build_meta(arch, "full")
    assert len(m.io.cameras) == 2
    wire = {"pi0": 224, "groot_n15": 224, "xr0": 256, "smolvla": 512}[arch]
    assert m.io.image_shape == (wire, wire, 3)


@pytest.mark.parametrize("arch", ARCHS)
def test_tiny_shapes_speed_and_handoff_spec(arch):
    m = build_model(arch, "tiny", seed=0)
    images, state, tokens, noise = inputs(m, 2)
    run(m, images, state, tokens, noise)  # first call pays one-off CPU kernel set-up
    t0 = time.perf_counter()
    with torch.no_grad():
        h = m.vlm_stage(images, state, tokens)
        a = m.action_stage(h, noise)
    assert time.perf_counter() - t0 < 1.0
    assert a.shape == (2, m.io.horizon, m.io.action_dim) and a.dtype == torch.float32
    assert torch.isfinite(a).all()
    assert {k: (tuple(v.shape), v.dtype) for k, v in h.items()} == m.handoff_spec(2)
    assert all(v.shape[0] == 2 for v in h.values())  # batch first in every handoff tensor


@pytest.mark.parametrize("arch", ARCHS)
def test_action_depends_on_handoff_and_noise(arch):
    m = build_model(arch, "tiny", seed=0)
    images, state, tokens, noise = inputs(m, 1)
    with torch.no_grad():
        h = m.vlm_stage(images, state, tokens)
        a = m.action_stage(h, noise)
        assert not torch.allclose(a, m.action_stage(h, noise + 0.5), atol=1e-4)
        for key, t in h.items():
            if t.dtype.is_floating_point:
                other = dict(h, **{key: t + 0.5 * torch.randn_like(t)})
                assert not torch.allclose(a, m.action_stage(other, noise), atol=1e-4), key
        assert not torch.allclose(a, m.action_stage(m.vlm_stage(255 - images, state, tokens), noise), atol=1e-4)
        tokens2 = tokens.clone()
        tokens2[0, 1] = tokens[0, 1] % 100 + 101
        assert not torch.allclose(a, m.action_stage(m.vlm_stage(images, state, tokens2), noise), atol=1e-4)


@pytest.mark.parametrize("arch", ARCHS)
def test_batch_equals_single_runs(arch):
    m = build_model(arch, "tiny", seed=1)
    images, state, tokens, noise = inputs(m, 3)
    batched = run(m, images, state, tokens, noise)
    for i in range(3):
        single = run(m, images[i:i + 1], state[i:i + 1], tokens[i:i + 1], noise[i:i + 1])
        torch.testing.assert_close(batched[i:i + 1], single, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("arch", ARCHS)
def test_same_seed_same_model(arch):
    a, b, c = (build_model(arch, "tiny", seed=s) for s in (5, 5, 6))
    x = inputs(a, 2)
    torch.testing.assert_close(run(a, *x), run(b, *x), atol=0, rtol=0)
    assert not torch.allclose(run(a, *x), run(c, *x))


@pytest.mark.parametrize("arch", ARCHS)
def test_wire_size_other_than_model_size_is_resized(arch):
    cls = get_architecture(arch)
    cfg = dataclasses.replace(cls.CONFIGS["tiny"], image_size=48)
    m = cls(cfg)
    m.init_weights(torch.Generator().manual_seed(0))
    m.eval()
    images, state, tokens, noise = inputs(m, 2)
    assert images.shape[2:] == (48, 48, 3)
    assert torch.isfinite(run(m, images, state, tokens, noise)).all()


def test_user_registered_architecture():
    from shared.models.cli import describe
    from shared.models.toy import ToyVLA

    @register("my_test_vla")
    class MyVLA(ToyVLA):
        ACTION_MODULES = ("act_in", "time_in", "act_mlp", "act_out")

    try:
        m = build_model("my_test_vla", "tiny", seed=0)
        images, state, tokens = m.example_inputs(2)
        assert m.action_stage(m.vlm_stage(images, state, tokens), m.noise(2)).shape == (2, 10, 7)
        listed = describe()
        assert listed["my_test_vla"]["action_params"] > 0 and "toy" not in listed
        with pytest.raises(ValueError, match="'my_test_vla' is already registered"):
            register("my_test_vla")(type("Other", (ToyVLA,), {}))
        with pytest.raises(ValueError, match="MyVLA is already registered as 'my_test_vla'"):
            register("my_test_vla_2")(MyVLA)  # one class under two names would rename the first
        assert build_model("my_test_vla", "tiny").arch == "my_test_vla" and "my_test_vla_2" not in _ARCHS
        with pytest.raises(ValueError, match=r"'pi0' is already registered \(by shared.models.pi0\)"):
            register("pi0")(type("MyPi0", (ToyVLA,), {}))
    finally:
        _ARCHS.pop("my_test_vla", None)


def _small_io() -> ModelIO:
    return ModelIO(cameras=("base",), image_shape=(8, 8, 3), state_dim=4, prompt_len=4, horizon=3, action_dim=2,
                   steps=2)


class _StockLayers(VLAModel):
    """A user's model as people write them: stock layers that initialise in _reset_parameters, a buffer, a
    bare parameter, and no init_weights of its own."""

    CONFIGS = {"tiny": 16}

    def __init__(self, width: int):
        super().__init__()
        self.io = _small_io()
        self.attn = torch.nn.TransformerEncoderLayer(width, 2, 32, batch_first=True)
        self.query = torch.nn.Parameter(torch.randn(3, width) * 0.02)
        self.register_buffer("scale", torch.full((width,), 0.5))
        self.head = torch.nn.Linear(width, 2)


def test_user_model_weights_are_seeded_and_initialised():
    register("test_stock_layers")(_StockLayers)
    try:
        a, b, c = (build_model("test_stock_layers", "tiny", seed=s) for s in (3, 3, 4))
        for key, value in a.state_dict().items():
            assert torch.isfinite(value).all(), key
            torch.testing.assert_close(b.state_dict()[key], value, atol=0, rtol=0)  # same seed, same weights
        torch.testing.assert_close(a.scale, torch.full((16,), 0.5))  # the constructor's buffer, not raw memory
        assert a.attn.self_attn.in_proj_weight.abs().max() > 0  # _reset_parameters ran (xavier), not zeros
        assert not torch.equal(a.attn.self_attn.in_proj_weight, c.attn.self_attn.in_proj_weight)
        assert not torch.equal(a.query, c.query)
    finally:
        _ARCHS.pop("test_stock_layers", None)


def test_user_module_taking_a_builtin_name_is_a_config_error(tmp_path):
    # A fresh process, as `robion up` is: the config's imports run before any built-in architecture is loaded.
    (tmp_path / "takes_pi0.py").write_text(
        "from shared.models import register\nfrom shared.models.toy import ToyVLA\n\n"
        "@register('pi0')\nclass MyPi0(ToyVLA):\n    pass\n")
    (tmp_path / "cluster.yaml").write_text(
        "imports: [takes_pi0]\nmodels:\n  - {name: a, arch: pi0}\nexecutors:\n  - {name: e0, models: [a]}\n")
    code = ("import sys\nfrom shared.config import ConfigError, load_config\n"
            "try:\n    load_config(sys.argv[1])\nexcept ConfigError as exc:\n    print('ConfigError:', exc)\n")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "cluster.yaml")], capture_output=True, text=True,
                         timeout=120, cwd=Path(__file__).resolve().parents[1])
    assert out.returncode == 0, out.stderr
    assert ("ConfigError: imports[0]: cannot import 'takes_pi0' (ValueError: architecture 'pi0' is already "
            "registered (by shared.models.pi0))") in out.stdout


class _Tied(VLAModel):
    """A user's model with an init of its own and tied weights (head.weight is embed.weight)."""

    CONFIGS = {"tiny": 8}

    def __init__(self, width: int):
        super().__init__()
        self.io = _small_io()
        self.embed = torch.nn.Embedding(16, width)
        self.head = torch.nn.Linear(width, 16, bias=False)
        self.head.weight = self.embed.weight

    def init_weights(self, generator: torch.Generator) -> None:
        with torch.no_grad():
            self.embed.weight.normal_(generator=generator)


class _NeedsRealValues(VLAModel):
    """A constructor that reads a value (a drop-path schedule as timm builds it): impossible on the meta device."""

    CONFIGS = {"tiny": 4}

    def __init__(self, depth: int):
        super().__init__()
        self.io = _small_io()
        self.rates = [x.item() for x in torch.linspace(0, 0.1, depth)]
        self.proj = torch.nn.Linear(4, 4)

    def handoff_spec(self, batch: int) -> dict:
        return {"h": ((batch, 4), torch.float32)}

    def init_weights(self, generator: torch.Generator) -> None:
        with torch.no_grad():
            self.proj.weight.normal_(generator=generator)


def test_tied_weights_stay_tied_and_meta_hostile_constructors_still_build(tmp_path):
    """A model built on the meta device and materialised with to_empty lost its tied weights (two tensors,
    initialised apart); a constructor that cannot run on the meta device failed inside build_model, and then
    in the memory estimate of a config with memory_gb (a traceback); saving tied weights failed in safetensors
    ("Some tensors share memory")."""
    register("test_tied")(_Tied)
    register("test_needs_real_values")(_NeedsRealValues)
    try:
        m = build_model("test_tied", "tiny", seed=1)
        assert m.head.weight is m.embed.weight and m.embed.weight.abs().max() > 0
        save_weights(m, str(tmp_path / "tied.safetensors"))
        other = load_weights(build_model("test_tied", "tiny", seed=2), str(tmp_path / "tied.safetensors"))
        assert torch.equal(other.embed.weight, m.embed.weight) and other.head.weight is other.embed.weight
        a, b = (build_model("test_needs_real_values", "tiny", seed=2) for _ in range(2))
        assert len(a.rates) == 4 and torch.equal(a.proj.weight, b.proj.weight)  # same seed, same weights
        assert model_bytes("test_needs_real_values", "tiny", 2) > model_bytes("test_needs_real_values", "tiny", 1) > 0
        with pytest.raises(ConfigError, match="cannot estimate the memory of test_tied"):  # no handoff_spec
            model_bytes("test_tied", "tiny", 1)
    finally:
        _ARCHS.pop("test_tied", None)
        _ARCHS.pop("test_needs_real_values", None)


def test_register_misuse_is_refused_where_it_happens():
    """`@register` without a name turned the class into a function and registered nothing; the mistake surfaced
    later as "unknown architecture"."""
    with pytest.raises(TypeError, match=r"use @register\(\"my_vla\"\)"):
        register(_Tied)
    with pytest.raises(TypeError, match="needs a VLAModel subclass"):
        register("test_not_a_vla")(torch.nn.Linear)
    assert "test_not_a_vla" not in _ARCHS
    # CONFIGS is read as a mapping by the config's checks and `robion models`: there it failed as a TypeError.
    no_sizes = type("NoSizes", (_Tied,), {"CONFIGS": None})
    with pytest.raises(TypeError, match=r"NoSizes.CONFIGS must be a dict of size name -> config, got NoneType"):
        register("test_no_sizes")(no_sizes)
    assert "test_no_sizes" not in _ARCHS

    # A class without the stages (as registered above for weights alone) was accepted in a cluster config, and
    # the executor's start failed on a bare NotImplementedError.
    register("test_no_action")(type("NoAction", (_Tied,), {}))
    try:
        with pytest.raises(ConfigError, match=r"models\[0\].arch: test_no_action \(NoAction\) does not implement "
                                              r"vlm_stage and action_stage"):
            config_from_dict({"models": [{"name": "m", "arch": "test_no_action", "size": "tiny"}],
                              "executors": [{"name": "e", "models": ["m"]}]})
        with pytest.raises(NotImplementedError, match="_Tied does not implement vlm_stage"):
            _Tied(8).vlm_stage(None, None, None)
    finally:
        _ARCHS.pop("test_no_action", None)


def test_a_users_model_with_a_small_vocabulary_gets_example_and_prompt_ids_below_it():
    """example_inputs drew ids up to 199 whatever the model's vocabulary: with 128 ids the default handoff_spec (run
    by the executor before serving) failed with an IndexError. And the byte tokenizer gave ordinary characters the
    model's pad id (pad_id 100: every "b"), which the model masks out as padding."""
    from shared.models.tokenizer import PromptTokenizer
    from shared.models.toy import ToyVLA

    m = ToyVLA(dataclasses.replace(ToyVLA.CONFIGS["tiny"], vocab=128))
    images, state, tokens = m.example_inputs(4, generator=torch.Generator().manual_seed(0))
    assert int(tokens.max()) < 128
    assert m.handoff_spec(4)  # ran the VLM stage on them
    ids = PromptTokenizer(8, 128, pad_id=100)("bob bob")
    assert ids[:8].tolist().count(100) == 0 and len(set(ids[1:8].tolist())) == 3  # b, o and space, none padding
    assert int(ids.max()) < 128
    assert PromptTokenizer(8, 512)("bob").tolist()[:4] == [1, 100, 113, 100]  # pad 0: the ids of before
