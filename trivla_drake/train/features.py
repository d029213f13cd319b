"""The cache of frozen System 2 / System 3 outputs for policy training, computed once.

Layout: CACHE/features/<key>/<episode fingerprint>.safetensors, one shard per episode, with
    q_vl             (N, S, D_llm)            System 2's Q_vl of each cached frame (all S tokens valid)
    dynamics_static  (N, T+1, C, H_p, W_p)    System 3's F_p of the static view
    dynamics_wrist   (N, T+1, C, H_p, W_p)    ... of the wrist view
    frame_index      (N,)                     the episode frames (every feature_stride-th)
<key> hashes the System 2/3 weights and configs and every training setting the features depend on
(image size, stride, dtype, noise seed, batch size, cameras), so another model or setting never reads
stale features (`FeatureKeys`); the episode fingerprint (`episode_content_fingerprint`) hashes the episode's
metadata and the sha256 of its data and video files, checked against the dataset's recorded checksums (a
corrupted file stops caching with an error naming it; a replaced video gets new features). Shards are written atomically (temporary file renamed),
so an interrupted caching run resumes with the episodes it did not finish; under torchrun the missing
episodes are split across ranks.

System 2 draws no noise, so System 3's outputs do not depend on it: every model with the same System 3
weights and settings has the same System 3 features. Each folder's cache_info.json records
`dynamics_key` (System 3's weights and settings alone), and a missing shard whose episode another
folder with that key holds (a lender) is not computed in full:
- an ablation arm without System 2 (use_system2 false) reads the lender's shard as it is
  (`feature_shards_borrowed` in the summary);
- a model with System 2 (a retrained System 2 on the same System 3) computes System 2's Q_vl only
  and writes a shard of its own with the lender's System 3 tensors copied in
  (`feature_shards_dynamics_copied`), so it depends on no other folder once written.
The lending folders are listed in cache_info.json and the summary: delete them and the episodes are
computed in full. A folder lends once a policy stage has run on it with this code, which writes its
`dynamics_key`.

Speed (train/throughput.py measures it): System 3 does its instruction's work once per batch, not once per frame
(nn/shared_instruction.py; the shards stay bit-identical), and on the CPU the missing episodes are computed by
`workers` threads at once (default: torch's thread count, i.e. TrainConfig.threads), each with its own copy of the
model and one torch thread: the cores are used better than by one episode at a time on several torch threads (the
`cpu` preset's small matrices split poorly, and threads that wait on each other stall on a busy machine).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import os
import queue
import uuid
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from trivla_drake.data.durable import atomic_write_text
from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.train.config import TrainConfig
from trivla_drake.train.datasets import episode_content_fingerprint, episode_fingerprint, resize_frames
from trivla_drake.train.distributed import DistEnv

FORMAT_VERSION = 3  # 2: System 3 features with the config's feature_noise; 3: the System 2/3 configs in the keys
_DTYPES = {"float16": torch.float16, "bfloat16": torch.bfloat16, "float32": torch.float32}


def hash_module_weights(module: torch.nn.Module | None, hasher: Any) -> None:
    """Feeds every parameter and buffer (name, shape, dtype, bytes) of `module` into `hasher`."""
    if module is None:
        hasher.update(b"<none>")
        return
    for name, tensor in sorted(module.state_dict().items()):
        t = tensor.detach().to("cpu").contiguous()
        hasher.update(f"{name}:{tuple(t.shape)}:{t.dtype};".encode())
        hasher.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")  # 0-dim too


def _weights_digest(module: torch.nn.Module | None) -> str:
    hasher = hashlib.sha256()
    hash_module_weights(module, hasher)
    return hasher.hexdigest()


def _section(config: Any) -> dict[str, Any] | None:
    """A System 2/3 config as JSON-able settings, without the local paths it was loaded from."""
    if config is None:
        return None
    return {k: v for k, v in dataclasses.asdict(config).items() if not k.endswith("_path")}


def _hashed(settings: dict[str, Any], *digests: str) -> str:
    hasher = hashlib.sha256(json.dumps({"format": FORMAT_VERSION, **settings}, sort_keys=True).encode())
    for digest in digests:
        hasher.update(digest.encode())
    return hasher.hexdigest()[:20]


class FeatureKeys:
    """The cache keys of one model and setting, each system's weights hashed once.

    `full`: System 2/3's weights and configs and every training setting the cached features depend on
    (image size, stride, dtype, noise seed, batch size, cameras), so another model or setting never
    reads stale features. `dynamics`: the same for System 3 alone (None without it), equal for two
    models whose System 3 features are equal, with or without System 2."""

    def __init__(self, model: TriVLA, config: TrainConfig):
        common = {
            "image_size": model.image_size,
            "feature_stride": config.features.stride,
            "feature_dtype": config.features.dtype,
            "feature_seed": config.features.seed,
            "feature_batch_size": config.features.batch_size,
            "static_camera": config.static_camera,
            "wrist_camera": config.wrist_camera,
        }
        vl = _section(model.config.vision_language if model.vision_language is not None else None)
        dyn = _section(model.config.dynamics if model.dynamics is not None else None)
        vl_weights, dyn_weights = _weights_digest(model.vision_language), _weights_digest(model.dynamics)
        self.full = _hashed({**common, "vision_language": vl, "dynamics": dyn}, vl_weights, dyn_weights)
        self.dynamics = None if dyn is None else _hashed({**common, "dynamics": dyn, "only": "dynamics"}, dyn_weights)


def feature_cache_key(model: TriVLA, config: TrainConfig) -> str:
    """The folder name of `model`'s cached features under `config` (FeatureKeys.full)."""
    return FeatureKeys(model, config).full


def dynamics_feature_key(model: TriVLA, config: TrainConfig) -> str | None:
    """The key of `model`'s System 3 features alone (FeatureKeys.dynamics)."""
    return FeatureKeys(model, config).dynamics


def _lenders(features_root: Path, dynamics_key: str, own: Path) -> list[Path]:
    """Other cache folders of models with this System 3 (their shards hold its features)."""
    found = []
    for info_path in sorted(features_root.glob("*/cache_info.json")):
        if info_path.parent == own:
            continue
        try:
            info = json.loads(info_path.read_text())
        except (OSError, ValueError):
            continue
        if info.get("dynamics_key") == dynamics_key:
            found.append(info_path.parent)
    return found


def _lent_shard(name: str, lenders: list[Path]) -> Path | None:
    """The first valid shard called `name` in the lender folders, or None."""
    return next((folder / name for folder in lenders if _shard_is_valid(folder / name)), None)


def _episode_seed(seed: int, fingerprint: str) -> int:
    return int(hashlib.sha256(f"{seed}:{fingerprint}".encode()).hexdigest()[:15], 16)


@torch.inference_mode()
def compute_episode_features(
    model: TriVLA, reader: LeRobotReader, episode: int, config: TrainConfig, dynamics_from: Path | None = None
) -> dict[str, torch.Tensor]:
    """System 2 and 3 outputs for every `feature_stride`-th frame of one episode (see module doc);
    with `dynamics_from`, a lender's shard of this episode, its System 3 tensors instead of System 3's."""
    length = int(reader.episodes[episode]["length"])
    frames_index = np.arange(0, length, config.features.stride)
    lent: dict[str, torch.Tensor] = {}
    if dynamics_from is not None:
        from safetensors import safe_open

        with safe_open(str(dynamics_from), framework="pt", device="cpu") as f:  # its Q_vl is not read
            if f.get_tensor("frame_index").tolist() != frames_index.tolist():
                raise RuntimeError(f"the lent shard {dynamics_from} holds other frames of episode {episode}")
            lent = {k: f.get_tensor(k) for k in ("dynamics_static", "dynamics_wrist")}
    static = resize_frames(reader.episode_video(episode, config.static_camera)[frames_index], model.image_size)
    wrist = resize_frames(reader.episode_video(episode, config.wrist_camera)[frames_index], model.image_size)
    instruction = reader.task_of(episode)
    dtype = _DTYPES[config.features.dtype]
    # Seeded from the metadata alone, as before the cache was keyed by content: "random" noise draws the same.
    generator = torch.Generator().manual_seed(_episode_seed(config.features.seed, episode_fingerprint(reader, episode)))
    parts: dict[str, list[torch.Tensor]] = {}
    run_dynamics = model.dynamics is not None and not lent
    # One instruction per episode: System 3 does its work once per batch (TriVLA.encode_dynamics_batch).
    for start in range(0, len(frames_index), config.features.batch_size):
        s = torch.from_numpy(np.ascontiguousarray(static[start : start + config.features.batch_size]))
        w = torch.from_numpy(np.ascontiguousarray(wrist[start : start + config.features.batch_size]))
        texts = [instruction] * len(s)
        if model.vision_language is not None:
            q_vl, mask = model.encode_vision_language_batch(s, w, texts)
            if not bool(mask.all()):  # one instruction per episode: no padding inside a shard
                raise RuntimeError("unexpected padding in System 2's tokens of one episode")
            parts.setdefault("q_vl", []).append(q_vl.float().cpu())
        if run_dynamics:
            f_static, f_wrist = model.encode_dynamics_batch(s, w, texts, generator=generator)
            parts.setdefault("dynamics_static", []).append(f_static.float().cpu())
            parts.setdefault("dynamics_wrist", []).append(f_wrist.float().cpu())
    out = {}
    for key, chunks in parts.items():
        full = torch.cat(chunks)
        converted = full.to(dtype)
        if not torch.isfinite(converted).all():
            raise ValueError(
                f"System {'2' if key == 'q_vl' else '3'} features of episode {episode} overflow "
                f"{config.features.dtype}: use features.dtype float32 (--set features.dtype=float32)"
            )
        out[key] = converted.contiguous()
    out.update(lent)
    out["frame_index"] = torch.from_numpy(frames_index.astype(np.int64))
    return out


def _save_shard(path: Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> None:
    from safetensors.torch import save_file

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp")
    save_file(tensors, str(tmp), metadata=metadata)
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _shard_is_valid(path: Path) -> bool:
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            return "frame_index" in f.keys()
    except Exception:  # noqa: BLE001 - a corrupt shard is recomputed
        return False


# A model is copied once per worker thread (`feature_workers`) only while it is smaller than this.
MAX_WORKER_COPY_BYTES = 2 * 1024**3


def _model_bytes(model: torch.nn.Module) -> int:
    return sum(t.numel() * t.element_size() for t in [*model.parameters(), *model.buffers()])


def feature_workers(model: TriVLA, workers: int | None) -> int:
    """How many episodes the cache computes at once: `workers` (None: torch's thread count, i.e. the cores this
    process was given, TrainConfig.threads), each on its own copy of the model with one torch thread; 1 on a GPU
    or for a model over MAX_WORKER_COPY_BYTES, which then uses torch's threads within each episode."""
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ValueError(f"feature cache workers must be an integer >= 1; got {workers!r}")
    if model.device.type != "cpu" or _model_bytes(model) > MAX_WORKER_COPY_BYTES:
        return 1
    return workers if workers is not None else max(1, torch.get_num_threads())


def _compute_shards(model: TriVLA, reader: LeRobotReader, episodes: list[int], config: TrainConfig,
                    copy_from: dict[int, Path], save: Callable[[int, dict[str, torch.Tensor]], None], workers: int,
                    done: Callable[[], None]) -> None:
    """Computes and `save`s the features of `episodes`, `workers` at a time (see `feature_workers`), calling
    `done()` after each; the first error stops the rest and is raised."""
    if workers <= 1 or len(episodes) <= 1:
        for episode in episodes:
            save(episode, compute_episode_features(model, reader, episode, config, copy_from.get(episode)))
            done()
        return
    workers = min(workers, len(episodes))
    replicas: queue.SimpleQueue = queue.SimpleQueue()
    for _ in range(workers):
        replicas.put(copy.deepcopy(model))

    def one(episode: int) -> None:
        torch.set_num_threads(1)  # this thread's own setting: the workers are the parallelism
        replica = replicas.get()
        try:
            save(episode, compute_episode_features(replica, reader, episode, config, copy_from.get(episode)))
        finally:
            replicas.put(replica)

    threads_before = torch.get_num_threads()
    try:
        with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="feature-cache") as pool:
            futures = [pool.submit(one, episode) for episode in episodes]
            try:
                for future in as_completed(futures):
                    future.result()
                    done()
            except BaseException:
                for future in futures:
                    future.cancel()
                raise
    finally:
        torch.set_num_threads(threads_before)  # a worker's setting also becomes new threads' default


def ensure_feature_cache(
    model: TriVLA,
    reader: LeRobotReader,
    episodes: list[int],
    config: TrainConfig,
    env: DistEnv,
    *,
    progress: bool = True,
    workers: int | None = None,
) -> tuple[dict[int, Path], dict[str, Any]]:
    """Computes the missing shards (split across ranks; within a rank, `workers` episodes at once: `feature_workers`),
    waits for all ranks, and returns episode -> shard path and a summary (folder, computed / reused shards, bytes per
    episode)."""
    from tqdm import tqdm

    workers = feature_workers(model, workers)

    if model.vision_language is None and model.dynamics is None:
        return {}, {"feature_cache": None}
    keys = FeatureKeys(model, config)
    key, dynamics_key = keys.full, keys.dynamics
    root = Path(config.cache_dir) / "features" / key
    shards = {e: root / f"{episode_content_fingerprint(reader, e)}.safetensors" for e in episodes}
    missing: list[int] = []
    copy_from: dict[int, Path] = {}  # episode -> lender shard whose System 3 tensors it copies
    if env.is_main:
        missing = [e for e in episodes if not (shards[e].is_file() and _shard_is_valid(shards[e]))]
        if dynamics_key is not None and missing:
            lenders = _lenders(root.parent, dynamics_key, root)
            lent = {e: shard for e in missing if (shard := _lent_shard(shards[e].name, lenders)) is not None}
            if model.vision_language is None:  # the lender's shard is this arm's
                shards.update(lent)
                missing = [e for e in missing if e not in lent]
            else:
                copy_from = lent
    # Rank 0's lists, so that every rank splits the same work and reads the same lent shards.
    missing, shards, copy_from = env.broadcast_object((missing, shards, copy_from))
    lenders = sorted({str(path.parent) for path in [*shards.values(), *copy_from.values()] if path.parent != root})
    borrowed = sum(path.parent != root for path in shards.values())
    mine = missing[env.rank :: env.world_size]
    if env.is_main:
        root.mkdir(parents=True, exist_ok=True)
        info = {
            "key": key,
            "preset": model.config.preset,
            "system2": model.vision_language is not None,
            "system3": model.dynamics is not None,
            "dynamics_key": dynamics_key,
            "lenders": lenders,
            "feature_stride": config.features.stride,
            "feature_dtype": config.features.dtype,
            "feature_seed": config.features.seed,
            "image_size": model.image_size,
        }
        info_path = root / "cache_info.json"
        try:  # another folder of the same run (extra_data) may have lent shards to this cache too
            earlier = json.loads(info_path.read_text()) if info_path.is_file() else {}
        except ValueError:
            earlier = {}
        if earlier.get("key") == key:
            info["lenders"] = sorted({*earlier.get("lenders", []), *lenders})
        atomic_write_text(info_path, json.dumps(info, indent=2))
    was_training = model.training
    model.eval()
    bar = tqdm(total=len(mine), desc="caching System 2/3 features", unit="ep",
               disable=not (progress and env.is_main) or not mine)

    def save(episode: int, tensors: dict[str, torch.Tensor]) -> None:
        _save_shard(shards[episode], tensors, {"instruction": reader.task_of(episode), "key": key})

    try:
        _compute_shards(model, reader, mine, config, copy_from, save, workers, lambda: bar.update(1))
    finally:
        bar.close()
        model.train(was_training)
    env.barrier()
    sample = [e for e in episodes if shards[e].parent == root][:50]  # lent shards hold Q_vl too: not counted
    total_bytes = sum(shards[e].stat().st_size for e in sample)
    cached_frames = sum(-(-int(reader.episodes[e]["length"]) // config.features.stride) for e in sample)
    summary = {
        "feature_cache": str(root),
        "feature_cache_lenders": lenders,
        "feature_shards_computed": len(missing),
        "feature_shards_reused": len(episodes) - len(missing) - borrowed,
        "feature_shards_borrowed": borrowed,
        "feature_shards_dynamics_copied": len(copy_from),
        "feature_cache_workers": workers,
        "feature_cache_bytes_per_episode": total_bytes / len(sample) if sample else None,
        "feature_cache_bytes_per_frame": total_bytes / cached_frames if sample else None,
    }
    return shards, summary
