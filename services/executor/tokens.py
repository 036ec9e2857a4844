"""Prompt tokenisation for the executor's I/O thread, cached per instruction string."""

from __future__ import annotations

from functools import lru_cache
from typing import Callable

import numpy as np

from shared.models.base import VLAModel
from shared.models.tokenizer import PromptTokenizer


# Instructions cached per model, and the longest one cached. A robot repeats its instruction on every call, and a
# fleet's instructions are short; any text up to 4096 characters is accepted, but caching those (16 KB a string of
# emoji) in a second cache besides the tokenizer's own held about 66 MB per model.
CACHED_INSTRUCTIONS = 4096
CACHED_CHARS = 256


def tokenizer_for(model: VLAModel, path: str | None = None) -> Callable[[str], np.ndarray]:
    """The model's prompt tokenizer (a tokenizer file when given, else byte-level) returning int64 ids."""
    tok = PromptTokenizer.for_model(model, path, cache_size=0)  # cached once, here

    def tokenize(text: str) -> np.ndarray:
        ids = np.asarray(tok.ids(text), dtype=np.int64)
        ids.setflags(write=False)
        return ids

    cached = lru_cache(maxsize=CACHED_INSTRUCTIONS)(tokenize)

    def encode(text: str) -> np.ndarray:
        return cached(text) if len(text) <= CACHED_CHARS else tokenize(text)

    encode.cache_info = cached.cache_info  # type: ignore[attr-defined]
    return encode
