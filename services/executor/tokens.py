"""Prompt tokenisation for the executor's I/O thread, cached per instruction string."""

from __future__ import annotations

from functools import lru_cache
from typing import Callable

import numpy as np

from shared.config import ModelConfig


def byte_tokenizer(prompt_len: int) -> Callable[[str], np.ndarray]:
    """UTF-8 bytes shifted past the pad id 0, padded or truncated to ``prompt_len``."""

    @lru_cache(maxsize=4096)  # a robot repeats its instruction on every call
    def encode(text: str) -> np.ndarray:
        ids = np.zeros(prompt_len, dtype=np.int64)
        raw = np.frombuffer(text.encode("utf-8")[:prompt_len], dtype=np.uint8).astype(np.int64) + 1
        ids[: len(raw)] = raw
        ids.setflags(write=False)
        return ids

    return encode


def tokenizer_for(model: ModelConfig, prompt_len: int) -> Callable[[str], np.ndarray]:
    return byte_tokenizer(prompt_len)
