"""Prompt text -> fixed-length token ids for the VLM stage.

A robot sends the same instruction on every call, so ids are cached per instruction
string (LRU). Without a tokenizer file, a byte-level fallback maps UTF-8 bytes to ids
(enough for serving random-weight models and for the demo); with one, the real
tokenizer is loaded from a local path: a Hugging Face ``tokenizer.json`` (package
``tokenizers``) or a SentencePiece ``.model`` file (package ``sentencepiece``).
"""

from __future__ import annotations

import os
from collections import OrderedDict
from threading import Lock

import torch

PAD_ID = 0
BOS_ID = 1
_BYTE_OFFSET = 2  # ids 0 and 1 are pad and BOS


class PromptTokenizer:
    """Encodes prompts to ``prompt_len`` ids: BOS + text, right-padded with ``pad_id`` or truncated."""

    def __init__(self, prompt_len: int, vocab_size: int, path: str | os.PathLike | None = None, pad_id: int = PAD_ID,
                 cache_size: int = 1024):
        if prompt_len < 1:
            raise ValueError("prompt_len must be >= 1")
        # A str or a path-like; "" is a file name that does not exist, not "no tokenizer" (a config's empty value
        # must not quietly serve byte ids to a model trained on real ones).
        path = os.fspath(path) if path is not None else None
        self.prompt_len, self.vocab_size, self.path, self.pad_id = prompt_len, vocab_size, path, pad_id
        self.cache_size = cache_size
        self._cache: OrderedDict[str, tuple[int, ...]] = OrderedDict()
        self._lock = Lock()  # the executor's I/O thread and others may share one tokenizer
        self.hits = self.misses = 0
        self._encode = self._load(path) if path is not None else self._bytes

    @classmethod
    def for_model(cls, model, path: str | None = None, cache_size: int = 1024) -> "PromptTokenizer":
        """The tokenizer matching a model's prompt length, vocabulary and pad id: its config's ``vocab`` and
        ``pad_id`` where it has them (every zoo model does). A user's model without them gets the byte-level
        ids as they are, all below 258 (pad, BOS and the 256 byte values)."""
        cfg = getattr(model, "cfg", None)
        return cls(model.io.prompt_len, getattr(cfg, "vocab", 256 + _BYTE_OFFSET), path,
                   getattr(cfg, "pad_id", PAD_ID), cache_size)

    # -- backends

    def _bytes(self, text: str) -> list[int]:
        # The byte ids step over a pad id among them: the models mask prompt positions by `ids != pad_id`, and a
        # user's model with pad_id 100 had every "b" (2 + 98) masked out as padding.
        skip = _BYTE_OFFSET <= self.pad_id < self.vocab_size
        span = self.vocab_size - _BYTE_OFFSET - skip
        if span < 1:
            raise ValueError(f"vocab_size {self.vocab_size} too small for the byte tokenizer")
        ids = (_BYTE_OFFSET + b % span for b in text.encode("utf-8"))
        return [BOS_ID] + [i + 1 if skip and i >= self.pad_id else i for i in ids]

    def _load(self, path: str):
        if not os.path.isfile(path):
            raise FileNotFoundError(f"tokenizer file not found: {path}")
        if path.endswith(".json"):
            try:
                from tokenizers import Tokenizer
            except ImportError as e:
                raise ImportError(f"loading {path} needs the 'tokenizers' package (pip install tokenizers)") from e
            try:
                tok = Tokenizer.from_file(path)
            except Exception as e:  # the library raises a bare Exception for a file it cannot parse
                raise ValueError(f"cannot load tokenizer {path}: {e}") from None
            # Padding and truncation are ours (to prompt_len, with the model's pad id): a file saved with its own
            # would fill prompts with its pad id, which the model then reads as text.
            tok.no_padding()
            tok.no_truncation()
            # A robot's instruction is text: "<pad>" or "<|im_start|>" in it was encoded as the special token itself,
            # so a client could put pad ids (read as padding) or control tokens mid-prompt.
            if not hasattr(tok, "encode_special_tokens"):  # 0.15.0 takes the assignment and ignores it
                raise ImportError(f"loading {path} needs tokenizers >= 0.15.1 (pip install -U tokenizers)")
            tok.encode_special_tokens = True
            # The largest id, not the entry count: a vocabulary with gaps has ids past its size.
            size = max(tok.get_vocab(with_added_tokens=True).values(), default=-1) + 1
            pad = tok.id_to_token(self.pad_id)
            specials = {i for i, added in tok.get_added_tokens_decoder().items() if added.special}
            if pad is not None and self.pad_id not in specials and "pad" not in pad.lower():
                self._pad_clash(path, pad)
            encode = lambda text: tok.encode(text).ids  # noqa: E731
        elif path.endswith(".model"):
            try:
                import sentencepiece as spm
            except ImportError as e:
                raise ImportError(f"loading {path} needs the 'sentencepiece' package "
                                  "(pip install sentencepiece)") from e
            try:
                sp = spm.SentencePieceProcessor(model_file=path)
            except RuntimeError as e:  # "could not parse ModelProto": not a sentencepiece model
                raise ValueError(f"cannot load tokenizer {path}: {e}") from None
            size = sp.get_piece_size()
            if self.pad_id < size and not sp.is_control(self.pad_id):
                self._pad_clash(path, sp.id_to_piece(self.pad_id))
            encode = lambda text: [sp.bos_id()] * (sp.bos_id() >= 0) + sp.encode(text)  # noqa: E731
        else:
            raise ValueError(f"unknown tokenizer format {path!r}: expected a tokenizers .json or a sentencepiece .model")
        if size > self.vocab_size:
            raise ValueError(f"tokenizer {path} has {size} ids but the model's vocabulary has {self.vocab_size}")
        return encode

    def _pad_clash(self, path: str, token: str) -> None:
        # The models mask prompt positions by `ids != pad_id`: a pad id that is also text would drop that text.
        raise ValueError(f"tokenizer {path}: id {self.pad_id}, the model's pad id, is the token {token!r}, not a "
                         f"pad or special token: every {token!r} in a prompt would be masked out as padding")

    # -- API

    def ids(self, text: str) -> tuple[int, ...]:
        """Fixed-length ids of one prompt (cached)."""
        with self._lock:
            hit = self._cache.get(text)
            if hit is not None:
                self._cache.move_to_end(text)
                self.hits += 1
                return hit
        ids = list(self._encode(text))[: self.prompt_len]
        out = tuple(ids + [self.pad_id] * (self.prompt_len - len(ids)))
        with self._lock:
            self.misses += 1
            self._cache[text] = out
            if len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return out

    def __call__(self, texts: str | list[str]) -> torch.Tensor:
        """int64 ``[prompt_len]`` for one string, ``[B, prompt_len]`` for a list."""
        if isinstance(texts, str):
            return torch.tensor(self.ids(texts), dtype=torch.int64)
        return torch.tensor([self.ids(t) for t in texts], dtype=torch.int64).view(len(texts), self.prompt_len)
