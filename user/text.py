"""Instructions as data: text <-> a fixed-size uint8 tensor, and a hub-free word tokenizer.

A language-conditioned robot puts its current instruction in the observation as UTF-8 bytes
(zero-padded to a fixed length), so it travels with every step through replay and inference like
any other feature and the learner trains on the instruction each step was taken under. No
torch here: edges import it.
"""

from __future__ import annotations

import functools
import re
import zlib

import numpy as np

INSTRUCTION_KEY = "instruction"
INSTRUCTION_BYTES = 64
_WORD = re.compile(r"[a-z0-9]+")


def encode_instruction(text: str, size: int = INSTRUCTION_BYTES) -> np.ndarray:
    """(size,) uint8: UTF-8 bytes, zero-padded; ValueError if it does not fit."""
    raw = text.encode("utf-8")
    if len(raw) > size:
        raise ValueError(f"instruction is {len(raw)} bytes, the feature holds {size}")
    out = np.zeros(size, dtype=np.uint8)
    out[: len(raw)] = np.frombuffer(raw, dtype=np.uint8)
    return out


def decode_instruction(array: np.ndarray) -> str:
    """The text in an encoded instruction (bytes up to the first zero; invalid UTF-8 replaced)."""
    raw = np.asarray(array, dtype=np.uint8).reshape(-1).tobytes()
    return raw.split(b"\0", 1)[0].decode("utf-8", errors="replace")


def word_ids(text: str, vocab_size: int, max_words: int) -> np.ndarray:
    """(max_words,) int64 ids in [1, vocab_size), 0 = padding. Words are hashed (crc32), so any text
    maps to ids without a vocabulary file; rare collisions only merge two words' embeddings.
    Read-only: a robot repeats its instruction every call, so the ids of recent texts are cached."""
    if vocab_size < 2:
        raise ValueError("vocab_size must be >= 2")
    return _cached_word_ids(text, vocab_size, max_words)


@functools.lru_cache(maxsize=4096)
def _cached_word_ids(text: str, vocab_size: int, max_words: int) -> np.ndarray:
    ids = np.zeros(max_words, dtype=np.int64)
    for i, word in enumerate(_WORD.findall(text.lower())[:max_words]):
        ids[i] = 1 + zlib.crc32(word.encode()) % (vocab_size - 1)
    ids.flags.writeable = False
    return ids
