"""Weights and tokenizer files that are not what their name says: a ValueError naming the file (which the
executor reports as `cannot load models: ...`, exit code 2), not a library exception and a traceback."""

import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

from shared.models import build_model
from shared.models.tokenizer import PromptTokenizer
from shared.models.weights import WeightsError, load_weights
from tests.helpers import cluster_config

ROOT = Path(__file__).resolve().parent.parent


def torch_checkpoint(tmp_path: Path) -> Path:
    """The usual mistake: a torch.save checkpoint where a safetensors file belongs."""
    path = tmp_path / "toy.pt"
    torch.save(build_model("toy", "tiny").state_dict(), path)
    return path


@pytest.mark.parametrize("content", [None, b"", b"not a safetensors file at all"])
def test_a_file_that_is_not_safetensors_raises_weights_error(tmp_path, content):
    path = torch_checkpoint(tmp_path) if content is None else tmp_path / "w.safetensors"
    if content is not None:
        path.write_bytes(content)
    model = build_model("toy", "tiny")
    before = {k: v.clone() for k, v in model.state_dict().items()}
    with pytest.raises(WeightsError, match=f"{path} is not a safetensors file"):
        load_weights(model, str(path))
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())


def test_executor_with_a_torch_checkpoint_as_weights_exits_2_with_the_reason(tmp_path):
    path, data = cluster_config(tmp_path)
    data["models"][0]["weights"] = str(torch_checkpoint(tmp_path))
    path.write_text(yaml.safe_dump(data))
    res = subprocess.run([sys.executable, "-m", "services.executor.main", "-c", str(path), "--name", "ex1"],
                         capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert "cannot load models" in res.stderr and "is not a safetensors file" in res.stderr, res.stderr


def test_a_corrupt_tokenizer_json_raises_value_error(tmp_path):
    pytest.importorskip("tokenizers")
    path = tmp_path / "tokenizer.json"
    path.write_text("{not json")
    with pytest.raises(ValueError, match=f"cannot load tokenizer {path}"):
        PromptTokenizer(8, 1000, path=str(path))


def test_a_corrupt_sentencepiece_model_raises_value_error(tmp_path):
    pytest.importorskip("sentencepiece")
    path = tmp_path / "tokenizer.model"
    path.write_bytes(b"garbage")
    with pytest.raises(ValueError, match=f"cannot load tokenizer {path}"):
        PromptTokenizer(8, 1000, path=str(path))
