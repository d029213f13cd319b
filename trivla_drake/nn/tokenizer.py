"""Text tokenizers: a deterministic UTF-8 byte-level one that needs no download, and an adapter
that gives a local pretrained (transformers) tokenizer the same small interface."""

from __future__ import annotations

import os
import re
from typing import Protocol

CHAT_SPECIAL_TOKENS: tuple[str, ...] = ("<|im_start|>", "<|im_end|>", "<img>", "</img>")
"""Markup of the chat-style prompt (ChatML as SmolLM2 uses, image delimiters as Eagle-2 uses)."""


class TextTokenizer(Protocol):
    """What the model needs from a tokenizer."""

    pad_token_id: int
    bos_token_id: int | None
    eos_token_id: int | None

    def encode(self, text: str, *, allow_special: bool = True) -> list[int]:
        """Token ids of `text`; with allow_special=False, markup like <|im_end|> is plain text."""
        ...

    def decode(self, ids: list[int]) -> str:
        """Text of `ids`."""
        ...

    @property
    def vocab_size(self) -> int:
        """One more than the largest id the tokenizer can return."""
        ...


class ByteTokenizer:
    """UTF-8 bytes are ids 0-255; special tokens follow. Deterministic, dependency-free, no download."""

    SPECIAL_TOKENS: tuple[str, ...] = ("<pad>", "<bos>", "<eos>") + CHAT_SPECIAL_TOKENS
    VOCAB_SIZE: int = 256 + len(SPECIAL_TOKENS)
    name = "byte"

    def __init__(self) -> None:
        self._special_ids = {tok: 256 + i for i, tok in enumerate(self.SPECIAL_TOKENS)}
        self._special_tokens = {i: tok for tok, i in self._special_ids.items()}
        pattern = "|".join(re.escape(tok) for tok in sorted(self.SPECIAL_TOKENS, key=len, reverse=True))
        self._split = re.compile(f"({pattern})")
        self.pad_token_id = self._special_ids["<pad>"]
        self.bos_token_id = self._special_ids["<bos>"]
        self.eos_token_id = self._special_ids["<eos>"]

    @property
    def vocab_size(self) -> int:
        """256 byte ids plus the special tokens."""
        return self.VOCAB_SIZE

    def token_id(self, token: str) -> int:
        """Id of a special token such as "<|im_start|>"."""
        return self._special_ids[token]

    def encode(self, text: str, *, allow_special: bool = True) -> list[int]:
        """UTF-8 bytes of `text`, with special-token strings mapped to their ids when allowed."""
        if not allow_special:
            return list(text.encode("utf-8"))
        ids: list[int] = []
        for piece in self._split.split(text):
            if piece in self._special_ids:
                ids.append(self._special_ids[piece])
            elif piece:
                ids.extend(piece.encode("utf-8"))
        return ids

    def decode(self, ids: list[int]) -> str:
        """Inverse of `encode` (invalid UTF-8 is replaced)."""
        out: list[str] = []
        buf = bytearray()
        for i in ids:
            if i < 256:
                buf.append(i)
                continue
            if buf:
                out.append(buf.decode("utf-8", errors="replace"))
                buf = bytearray()
            out.append(self._special_tokens.get(i, ""))
        if buf:
            out.append(buf.decode("utf-8", errors="replace"))
        return "".join(out)


class PretrainedTokenizer:
    """Adapts a transformers tokenizer loaded from a local directory to the `TextTokenizer` interface."""

    name = "pretrained"

    def __init__(self, hf_tokenizer, source: str | None = None) -> None:
        self.hf_tokenizer = hf_tokenizer
        self.source = source
        pad = hf_tokenizer.pad_token_id
        if pad is None:
            pad = hf_tokenizer.eos_token_id if hf_tokenizer.eos_token_id is not None else 0
        self.pad_token_id = int(pad)
        self.bos_token_id = hf_tokenizer.bos_token_id
        self.eos_token_id = hf_tokenizer.eos_token_id

    @property
    def vocab_size(self) -> int:
        """Size of the vocabulary including added tokens."""
        return len(self.hf_tokenizer)

    def encode(self, text: str, *, allow_special: bool = True) -> list[int]:
        """Token ids of `text` without the tokenizer's automatic BOS/EOS."""
        return list(
            self.hf_tokenizer.encode(text, add_special_tokens=False, split_special_tokens=not allow_special)
        )

    def decode(self, ids: list[int]) -> str:
        """Text of `ids`."""
        return self.hf_tokenizer.decode(ids)

    def save(self, directory: str) -> None:
        """Writes the tokenizer files to `directory`."""
        self.hf_tokenizer.save_pretrained(directory)


def load_tokenizer(path: str | None) -> ByteTokenizer | PretrainedTokenizer:
    """The byte-level tokenizer for None, else the transformers tokenizer stored in local directory `path`."""
    if path is None:
        return ByteTokenizer()
    if not os.path.isdir(path):
        raise ValueError(f"tokenizer path {path!r} is not a directory (pretrained files are never downloaded)")
    from transformers import AutoTokenizer

    return PretrainedTokenizer(AutoTokenizer.from_pretrained(path, local_files_only=True), source=path)
