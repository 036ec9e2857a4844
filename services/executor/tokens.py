"""Prompt tokenisation for the executor's I/O thread, cached per instruction string."""

from __future__ import annotations

from functools import lru_cache
from typing import Callable

import numpy as np

from shared.models.base import VLAModel
from shared.models.tokenizer import PromptTokenizer


def tokenizer_for(model: VLAModel, path: str | None = None) -> Callable[[str], np.ndarray]:
    """The model's prompt tokenizer (a tokenizer file when given, else byte-level) returning int64 ids."""
    tok = PromptTokenizer.for_model(model, path)

    @lru_cache(maxsize=4096)  # a robot repeats its instruction on every call
    def encode(text: str) -> np.ndarray:
        ids = np.asarray(tok.ids(text), dtype=np.int64)
        ids.setflags(write=False)
        return ids

    return encode
