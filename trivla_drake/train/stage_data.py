"""Each stage's training data, prepared once and cached (decoded clips, the generated VQA set, System 2/3 features),
and the checks a policy run's datasets must pass against its model."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np

from trivla_drake.nn.trivla import TriVLA
from trivla_drake.train.config import TrainConfig
from trivla_drake.train.distributed import DistEnv


def check_grounding(reader, grounding_weight: float, where: str) -> None:
    """A System 1 with instruction grounding trains its sub-goal loss: it needs a positive
    `grounding_weight` and the dataset's tool-centre-point poses (the labels, data/subgoals.py)."""
    from trivla_drake.data.samples import TCP_POSE_KEY

    if not grounding_weight > 0:
        raise ValueError(f"{where} has System 1's instruction grounding: its sub-goal loss needs "
                         f"policy.grounding.weight > 0; got {grounding_weight}")
    if TCP_POSE_KEY not in reader.features:
        raise ValueError(f"policy.grounding.weight trains on sub-goals from {TCP_POSE_KEY!r}, "
                         f"which dataset {reader.root} does not have")


def check_resumed_normalization(saved, fitted, where: str) -> None:
    """A resumed policy run keeps training on the data it started on: ValueError naming data / extra_data
    when the statistics those folders give now differ from the checkpoint's (other or more folders)."""
    saved_dict, fitted_dict = saved.to_dict(), fitted.to_dict()
    differing = [k for k in saved_dict if not np.allclose(saved_dict[k], fitted_dict[k], rtol=1e-5, atol=1e-7)]
    if differing:
        raise ValueError(f"data / extra_data give other statistics ({', '.join(differing)}) "
                         f"than {where} was trained on: resume on the same folders (or start a new run with --init)")


def prepare_data(config: TrainConfig, model: TriVLA, readers: list, env: DistEnv) -> tuple[Any, Callable, dict]:
    """(dataset, collate function, summary) of the stage; caches are made here (sharded over ranks).
    `readers`: `data`'s dataset, then `extra_data`'s (policy stage); empty for the vlm stage."""
    from trivla_drake.train import datasets as ds

    progress = config.progress and env.is_main
    reader = readers[0] if readers else None
    if config.stage == "video":
        episodes = list(range(reader.num_episodes))
        dyn = model.config.dynamics
        store = ds.FrameStore(reader, [config.static_camera, config.wrist_camera], dyn.video_size,
                              Path(config.cache_dir) / "clips")
        missing = env.broadcast_object(store.missing(episodes))  # rank 0's list: ranks split the same work
        from tqdm import tqdm

        for episode, camera in tqdm(missing[env.rank :: env.world_size], desc="decoding clips", unit="video",
                                    disable=not progress or not missing):
            store.make(episode, camera)
        env.barrier()
        stride = config.video.future_stride or ds.clip_stride(reader.fps, dyn.num_frames, config.video.clip_seconds)
        dataset = ds.VideoClipDataset(store, episodes, dyn.num_frames, stride)
        return dataset, ds.collate_video, {
            "episodes": len(episodes), "samples": len(dataset), "future_stride": stride,
            "clip_seconds": (dyn.num_frames - 1) * stride / reader.fps, "clip_cache": str(store.root),
            "clip_videos_decoded": len(missing),
        }
    if config.stage == "vlm":
        from trivla_drake.train import vqa

        folder = vqa_folder(config, model)
        settings = vqa.vqa_settings(scenes=config.vlm.vqa_scenes, questions_per_scene=config.vlm.vqa_questions_per_scene,
                                    seed=config.vlm.vqa_seed, image_size=model.image_size)
        error = None
        if env.is_main:
            try:
                vqa.ensure_vqa_set(folder, settings, progress=progress)
            except Exception as exc:  # noqa: BLE001 - re-raised on every rank below
                error = f"{type(exc).__name__}: {exc}"
        error = env.broadcast_object(error)
        if error is not None:
            raise ValueError(f"cannot make the VQA set in {folder}: {error}")
        dataset = vqa.VQADataset(folder, "train")
        return dataset, vqa.collate_vqa, {"vqa_folder": str(folder), "samples": len(dataset)}
    # policy
    from trivla_drake.train.features import ensure_feature_cache

    from trivla_drake.train.dataset_union import PolicyDatasetUnion, check_each_folder_adds, drop_repeated_episodes

    chosen = [list(range(r.num_episodes)) for r in readers]
    chosen, repeated = drop_repeated_episodes(readers, chosen)
    parts, summary = [], {}
    check_each_folder_adds(readers, chosen)
    for r, episodes in zip(readers, chosen):
        shards, summary_r = ensure_feature_cache(model, r, episodes, config, env, progress=progress)
        for key, value in summary_r.items():  # shard counts add up; the rest (one cache folder) is the first's
            if key not in summary:
                summary[key] = value
            elif key.startswith("feature_shards_"):
                summary[key] += value
        parts.append(ds.PolicyFeatureDataset(
            r, episodes, shards, feature_stride=config.features.stride,
            action_horizon=model.config.policy.action_horizon,
            use_system2=model.vision_language is not None, use_system3=model.dynamics is not None,
            grounding_frames_only=config.policy.grounding.phase == "bind",
            grounding_carry_tasks=tuple(config.policy.grounding.carry_tasks),
        ))
    dataset = parts[0] if len(parts) == 1 else PolicyDatasetUnion(parts)
    if len(parts) > 1:
        summary["episodes_per_dataset"] = {str(r.root): len(e) for r, e in zip(readers, chosen)}
        summary["repeated_episodes_dropped"] = repeated
    return dataset, ds.collate_policy, {"episodes": sum(map(len, chosen)), "samples": len(dataset), **summary}


def vqa_folder(config: TrainConfig, model: TriVLA) -> Path:
    """Where the vlm stage's VQA set lives: `data` unless that is a LeRobot dataset, else the cache."""
    from trivla_drake.train import vqa

    if config.data and not (Path(config.data) / "meta" / "info.json").is_file():
        return Path(config.data)
    if config.data and int(os.environ.get("RANK", "0")) == 0:
        print(f"trivla-drake train: note: {config.data} is a LeRobot dataset; the vlm stage renders its own "
              "scenes and does not use it", file=sys.stderr)
    settings = vqa.vqa_settings(scenes=config.vlm.vqa_scenes, questions_per_scene=config.vlm.vqa_questions_per_scene,
                                seed=config.vlm.vqa_seed, image_size=model.image_size)
    return Path(config.cache_dir) / "vqa" / vqa.vqa_key(settings)


def fit_policy_normalization(config: TrainConfig, model: TriVLA, readers: list, resume_from: Path | None, *,
                             note: Callable[[str], None]) -> None:
    """Checks a policy run's datasets (`data`, then `extra_data`) against `model` (state and action spaces, the
    grounding's labels, the cameras, one fps and one set of features) and sets the model's normalisation to their
    statistics; a resumed run's must be its checkpoint's. `note(message)` tells of narrowed action ranges."""
    from trivla_drake.train.dataset_union import check_same_features, check_same_fps, union_normalization
    from trivla_drake.train.datasets import check_cameras, check_spaces, narrowed_action_ranges

    where = f"checkpoint {resume_from}" if resume_from else (f"--init checkpoint {config.init}" if config.init
                                                             else f"preset {config.preset!r}")
    for one in readers:
        check_spaces(one, model.config, where)
        if model.policy.grounding is not None:
            check_grounding(one, config.policy.grounding.weight, where)
        if model.vision_language is not None or model.dynamics is not None:
            check_cameras(one, [config.static_camera, config.wrist_camera])
    check_same_fps(readers)
    check_same_features(readers)
    fitted = union_normalization(readers, model.config)
    if resume_from is not None:
        check_resumed_normalization(model.normalization, fitted, where)
    if config.init and resume_from is None:
        narrowed = narrowed_action_ranges(model.normalization, fitted, model.config.action_names)
        if narrowed:
            note(f"--data's action ranges are narrower than {where}'s, so its outputs are rescaled: "
                 f"{'; '.join(narrowed)}")
    model.set_normalization(fitted)
