"""Prompts, weights files and the `robion models` listing."""

import json
import sys

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from shared.models import build_model
from shared.models.cli import main as models_main
from shared.models.tokenizer import PromptTokenizer
from shared.models.weights import WeightsError, load_model, load_weights, save_weights


# --------------------------------------------------------------------------- tokenizer

def test_byte_tokenizer_pads_truncates_and_caches():
    tok = PromptTokenizer(prompt_len=8, vocab_size=300)
    ids = tok("pick")
    assert ids.dtype == torch.int64 and ids.shape == (8,)
    assert ids[0] == 1 and (ids[5:] == 0).all() and (ids[1:5] > 1).all()
    long = tok("put the red block in the bowl")
    assert long.shape == (8,) and (long != 0).all()
    batch = tok(["pick", "place", "pick"])
    assert batch.shape == (3, 8) and torch.equal(batch[0], batch[2])
    assert tok.hits >= 2 and tok.misses == 3
    assert int(tok("ünïcode ✓").max()) < 300


def test_byte_tokenizer_cache_is_lru_bounded():
    tok = PromptTokenizer(prompt_len=4, vocab_size=64, cache_size=2)
    for text in ["a", "b", "c", "a"]:
        tok(text)
    assert len(tok._cache) == 2 and tok.misses == 4
    assert int(tok("zzzz").max()) < 64


def test_tokenizer_for_model_matches_io():
    m = build_model("smolvla", "tiny")
    tok = PromptTokenizer.for_model(m)
    tokens = tok(["open the drawer", "close it"])
    images, state, _ = m.example_inputs(2)
    with torch.no_grad():
        out = m.action_stage(m.vlm_stage(images, state, tokens), m.noise(2))
    assert out.shape == (2, m.io.horizon, m.io.action_dim)


def test_tokenizer_file_errors(tmp_path, monkeypatch):
    with pytest.raises(FileNotFoundError, match="tokenizer file not found"):
        PromptTokenizer(8, 100, path=str(tmp_path / "missing.json"))
    bad = tmp_path / "vocab.txt"
    bad.write_text("x")
    with pytest.raises(ValueError, match="unknown tokenizer format"):
        PromptTokenizer(8, 100, path=str(bad))
    js = tmp_path / "tokenizer.json"
    js.write_text("{}")
    monkeypatch.setitem(sys.modules, "tokenizers", None)  # simulate the package being absent
    with pytest.raises(ImportError, match="tokenizers"):
        PromptTokenizer(8, 100, path=str(js))


def test_tokenizer_path_forms(tmp_path):
    with pytest.raises(FileNotFoundError, match="tokenizer file not found"):
        PromptTokenizer(8, 100, path="")  # an empty path is no file, not the byte-level fallback
    with pytest.raises(FileNotFoundError, match="tokenizer file not found"):
        PromptTokenizer(8, 100, path=tmp_path / "missing.model")  # a pathlib.Path is a path too


def test_real_tokenizer_sentencepiece(tmp_path):
    spm = pytest.importorskip("sentencepiece")
    lines = ["pick up the red cup", "open the top drawer", "put the cup in the drawer"] * 20
    spm.SentencePieceTrainer.train(sentence_iterator=iter(lines), model_prefix=str(tmp_path / "sp"), vocab_size=13,
                                   model_type="word", bos_id=1, eos_id=-1, pad_id=0, unk_id=2,
                                   minloglevel=2)
    sp = spm.SentencePieceProcessor(model_file=str(tmp_path / "sp.model"))
    tok = PromptTokenizer(8, 100, path=tmp_path / "sp.model")
    ids = tok("pick up the cup").tolist()
    assert ids == ([1] + sp.encode("pick up the cup") + [0] * 8)[:8]
    assert ids[1:5] != [0, 0, 0, 0] and len(set(ids[1:5])) == 4  # four known words, four ids
    with pytest.raises(ValueError, match="vocabulary"):
        PromptTokenizer(8, 10, path=str(tmp_path / "sp.model"))


def test_real_tokenizer_json(tmp_path):
    tokenizers = pytest.importorskip("tokenizers")
    from tokenizers.models import WordLevel
    from tokenizers.pre_tokenizers import Whitespace

    t = tokenizers.Tokenizer(WordLevel({"<pad>": 0, "<unk>": 1, "pick": 2, "up": 3, "cup": 4}, unk_token="<unk>"))
    t.pre_tokenizer = Whitespace()
    path = str(tmp_path / "tokenizer.json")
    t.save(path)
    tok = PromptTokenizer(6, 100, path=path)
    assert tok("pick up cup now").tolist() == [2, 3, 4, 1, 0, 0]
    # Special tokens spelt out in an instruction are text, not the tokens: "<pad>" was encoded as the pad id.
    t.add_special_tokens(["<s>"])
    t.save(path)
    ids = PromptTokenizer(12, 100, path=path)("pick <pad> up <s> cup").tolist()
    assert ids == [2, 1, 1, 1, 3, 1, 1, 1, 4, 0, 0, 0], ids  # "<", "pad", ">" are unknown words here
    with pytest.raises(ValueError, match="vocabulary"):
        PromptTokenizer(6, 3, path=path)


# --------------------------------------------------------------------------- weights

def test_weights_round_trip_is_a_fine_tuned_variant(tmp_path):
    path = str(tmp_path / "pi0_ft.safetensors")
    a, b = build_model("pi0", "tiny", seed=1), build_model("pi0", "tiny", seed=2)
    save_weights(a, path)
    images, state, tokens = a.example_inputs(2, generator=torch.Generator().manual_seed(0))
    noise = a.noise(2)
    with torch.no_grad():
        before = b.action_stage(b.vlm_stage(images, state, tokens), noise)
        load_weights(b, path)
        after = b.action_stage(b.vlm_stage(images, state, tokens), noise)
        want = a.action_stage(a.vlm_stage(images, state, tokens), noise)
    assert not torch.allclose(before, want)
    torch.testing.assert_close(after, want, atol=0, rtol=0)
    c = load_model("pi0", "tiny", path=path)  # built with seed 0, then every tensor from the file
    for key, value in a.state_dict().items():
        torch.testing.assert_close(c.state_dict()[key], value, atol=0, rtol=0)
    assert not torch.equal(build_model("pi0", "tiny").state_dict()["embed.weight"], a.state_dict()["embed.weight"])


def test_weights_errors(tmp_path):
    m = build_model("xr0", "tiny")
    with pytest.raises(FileNotFoundError, match="weights file not found"):
        load_weights(m, str(tmp_path / "nope.safetensors"))
    with pytest.raises(IsADirectoryError, match="is a directory"):  # it said "not found"
        load_weights(m, str(tmp_path))
    sd = {k: v.clone() for k, v in m.state_dict().items()}

    missing = dict(sd)
    missing.pop("dit.sink")
    save_file(missing, str(tmp_path / "missing.safetensors"))
    with pytest.raises(WeightsError, match=r"1 missing key\(s\): dit.sink"):
        load_weights(m, str(tmp_path / "missing.safetensors"))

    extra = dict(sd, **{"dit.extra": torch.zeros(3)})
    save_file(extra, str(tmp_path / "extra.safetensors"))
    with pytest.raises(WeightsError, match=r"unexpected key\(s\): dit.extra"):
        load_weights(m, str(tmp_path / "extra.safetensors"))

    shaped = dict(sd, **{"dit.sink": torch.zeros(2, sd["dit.sink"].shape[1])})
    save_file(shaped, str(tmp_path / "shape.safetensors"))
    before = m.state_dict()["embed.weight"].clone()
    with pytest.raises(WeightsError, match=r"shape mismatch.*dit.sink: file \[2, 32\] vs model \[1, 32\]"):
        load_weights(m, str(tmp_path / "shape.safetensors"))
    torch.testing.assert_close(m.state_dict()["embed.weight"], before)  # untouched on error

    save_weights(build_model("smolvla", "tiny"), str(tmp_path / "other.safetensors"))
    with pytest.raises(WeightsError, match="saved from 'smolvla', model is 'xr0'"):
        load_weights(m, str(tmp_path / "other.safetensors"))

    # A cast would turn these into weights: integers, and a value beyond float32 (inf), or a NaN.
    ints = dict(sd, **{"dit.sink": torch.ones_like(sd["dit.sink"], dtype=torch.int32)})
    save_file(ints, str(tmp_path / "ints.safetensors"))
    with pytest.raises(WeightsError, match=r"cannot hold the model's values: dit.sink: file I32 vs model float32"):
        load_weights(m, str(tmp_path / "ints.safetensors"))
    for bad_value in (1e39, float("nan")):
        huge = dict(sd, **{"dit.sink": torch.full(sd["dit.sink"].shape, bad_value, dtype=torch.float64)})
        save_file(huge, str(tmp_path / "huge.safetensors"))
        with pytest.raises(WeightsError, match="dit.sink holds NaN or infinite values as float32"):
            load_weights(m, str(tmp_path / "huge.safetensors"))
    torch.testing.assert_close(m.state_dict()["embed.weight"], before)
    assert torch.isfinite(m.state_dict()["dit.sink"]).all()

    (tmp_path / "torch.pt").write_bytes(b"PK\x03\x04" + bytes(64))  # a zip (torch.save) checkpoint, not safetensors
    (tmp_path / "cut.safetensors").write_bytes((tmp_path / "other.safetensors").read_bytes()[:100])
    for name in ("torch.pt", "cut.safetensors"):
        with pytest.raises(WeightsError, match="not a safetensors file"):
            load_weights(m, str(tmp_path / name))


# --------------------------------------------------------------------------- CLI

def test_models_cli_json(capsys):
    assert models_main(["--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert {"pi0", "smolvla", "groot_n15", "xr0"} <= set(info) and "toy" not in info
    assert info["pi0"] == {"vlm_params": info["pi0"]["vlm_params"], "action_params": info["pi0"]["action_params"],
                           "cameras": 2, "horizon": 50, "action_dim": 32, "steps": 10}
    assert info["groot_n15"]["steps"] == 4 and info["xr0"]["horizon"] == 30
    assert all(isinstance(v, int) for r in info.values() for v in r.values())


def test_models_cli_table(capsys):
    assert models_main([]) == 0
    out = capsys.readouterr().out
    assert "pi0" in out and "xr0" in out and "VLM params" in out
    pi0 = next(line.split() for line in out.splitlines() if line.startswith("pi0 "))
    assert pi0[1:3] == ["2.92B", "315M"]
    assert models_main(["--size", "tiny"]) == 0
    rows = {line.split()[0]: line.split() for line in capsys.readouterr().out.splitlines()[1:]}
    assert rows["pi0"][1].endswith("K") and rows["pi0"][2] != "0.0M"  # small stages keep their digits


def test_models_cli_names_what_it_cannot_list(capsys, monkeypatch):
    from shared.models import VLAModel, register
    from shared.models.registry import _ARCHS
    from shared.models.toy import ToyVLA

    class MetaHostile(VLAModel):
        CONFIGS = {"full": None}

        def __init__(self, cfg):
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(3))
            self.w.sum().item()  # not on the meta device

    register("test_meta_hostile")(MetaHostile)
    register("test_tiny_only")(type("TinyOnly", (ToyVLA,), {"CONFIGS": {"tiny": ToyVLA.CONFIGS["tiny"]}}))
    try:
        assert models_main(["--json"]) == 1
        captured = capsys.readouterr()
        listed = json.loads(captured.out)
        assert {"pi0", "smolvla", "groot_n15", "xr0"} <= set(listed)  # the rest still listed
        assert "test_meta_hostile: cannot be described" in captured.err
        assert "test_tiny_only: no size 'full' (sizes: tiny)" in captured.err
        assert models_main(["--json", "--size", "tiny"]) == 0  # the hostile one has no tiny size: only a note
        assert "test_tiny_only" in json.loads(capsys.readouterr().out)
    finally:
        _ARCHS.pop("test_meta_hostile", None)
        _ARCHS.pop("test_tiny_only", None)


def test_real_tokenizer_edge_cases_are_caught_at_load(tmp_path):
    """Three ways a tokenizer.json loaded without complaint and then served wrong prompts."""
    tokenizers = pytest.importorskip("tokenizers")
    from tokenizers.models import WordLevel
    from tokenizers.pre_tokenizers import Whitespace

    def saved(vocab: dict, name: str, padding: bool = False) -> str:
        t = tokenizers.Tokenizer(WordLevel(vocab, unk_token="<unk>"))
        t.pre_tokenizer = Whitespace()
        if padding:
            t.enable_padding(length=6, pad_id=1, pad_token="<unk>")
        path = str(tmp_path / name)
        t.save(path)
        return path

    # ids with gaps: 4 entries but id 600, past a 512-id vocabulary (the embedding raised IndexError per request)
    with pytest.raises(ValueError, match="vocabulary"):
        PromptTokenizer(6, 512, path=saved({"<pad>": 0, "<unk>": 1, "pick": 5, "cup": 600}, "gaps.json"))
    # a file saved with padding of its own filled prompts with its pad id, read by the model as text
    tok = PromptTokenizer(8, 100, path=saved({"<pad>": 0, "<unk>": 1, "pick": 2, "up": 3}, "padded.json", True))
    assert tok("pick up").tolist() == [2, 3, 0, 0, 0, 0, 0, 0]
    # the model's pad id is real text here ("!" is id 0, as in Qwen's vocabulary): every "!" would be masked out
    with pytest.raises(ValueError, match="masked out"):
        PromptTokenizer(6, 100, path=saved({"!": 0, "<unk>": 1, "stop": 2}, "bang.json"))


def test_a_sentencepiece_model_whose_pad_id_is_text_is_refused(tmp_path):
    spm = pytest.importorskip("sentencepiece")
    lines = ["pick up the red cup", "open the top drawer"] * 20
    spm.SentencePieceTrainer.train(sentence_iterator=iter(lines), model_prefix=str(tmp_path / "sp"), vocab_size=11,
                                   model_type="word", minloglevel=2)  # defaults: unk 0, bos 1, eos 2, no pad
    with pytest.raises(ValueError, match="masked out"):
        PromptTokenizer(8, 100, path=tmp_path / "sp.model")


def test_qwen_based_models_pad_with_qwens_pad_token():
    """Qwen's id 0 is "!"; its pad token <|endoftext|> is 151643. GR00T N1.5 and XR0 padded with 0."""
    from shared.models.groot_n15 import GR00TN15
    from shared.models.xr0 import XR0

    assert XR0.CONFIGS["full"].pad_id == 151643 < XR0.CONFIGS["full"].vocab
    assert GR00TN15.CONFIGS["full"].pad_id == 151643 < GR00TN15.CONFIGS["full"].vocab


def test_integer_and_boolean_tensors_take_only_their_kind_from_a_file(tmp_path):
    """Float data for an index or a mask was cast silently: 3.99 became 3, NaN became -2**63, 0.1 became True."""
    from safetensors.torch import save_file

    class Indexed(torch.nn.Module):
        arch = "indexed"

        def __init__(self):
            super().__init__()
            self.register_buffer("index", torch.arange(4))
            self.register_buffer("keep", torch.ones(4, dtype=torch.bool))

    m = Indexed()
    save_file({"index": torch.tensor([0.9, 1.5, float("nan"), 3.99], dtype=torch.float64),
               "keep": torch.tensor([0.1, 0.0, -3.0, 0.0])}, str(tmp_path / "floats.safetensors"))
    with pytest.raises(WeightsError, match="index: file F64 vs model int64.*keep: file F32 vs model bool"):
        load_weights(m, str(tmp_path / "floats.safetensors"))
    assert m.index.tolist() == [0, 1, 2, 3] and m.keep.all()  # unchanged
    save_file({"index": torch.tensor([3, 2, 1, 0], dtype=torch.int32), "keep": torch.tensor([True, False] * 2)},
              str(tmp_path / "ints.safetensors"))
    load_weights(m, str(tmp_path / "ints.safetensors"))
    assert m.index.tolist() == [3, 2, 1, 0] and m.keep.tolist() == [True, False, True, False]


def test_a_size_no_architecture_has_is_a_usage_error(capsys):
    """`robion models --size bogus` printed an empty table and exited 0."""
    from shared.models.cli import main as models_main

    assert models_main(["--size", "bogus"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and "no architecture has the size 'bogus'" in err and "pi0: no size 'bogus'" in err


def test_the_executors_instruction_cache_holds_short_instructions_once():
    """Every instruction was cached twice (the executor's cache and the tokenizer's own), up to 4096 characters each:
    about 66 MB per model for a flood of distinct long instructions. Short ones are cached once now, long ones not."""
    from services.executor.tokens import CACHED_CHARS, tokenizer_for

    encode = tokenizer_for(build_model("smolvla", "tiny"))
    short, long = "pick up the red block", "é" * (CACHED_CHARS + 1)
    for _ in range(3):
        a, b = encode(short), encode(long)
    assert encode.cache_info().currsize == 1 and encode.cache_info().hits == 2
    assert np.array_equal(encode(long), b) and not b.flags.writeable and not a.flags.writeable
    tok = PromptTokenizer.for_model(build_model("smolvla", "tiny"))
    assert tuple(a) == tok.ids(short) and tuple(b) == tok.ids(long)
