"""The shipped recipe's last training stage: re-fits a checkpoint's instruction-grounding read-out on rendered grounding
scenes mixed with a dataset's grounding frames (train/grounding_refit.py, train/grounding_scenes.py), measures the
sub-goal's error on unseen rendered scenes and on the dataset's frames before and after, and writes the model (float16,
as models/trivla_cpu) and a JSON report.

Killed and run again, the job starts training at once: the rendered scenes (grounding_scenes/, keyed by their settings)
and System 2's Q_vl of every set (grounding_q_vl/, keyed by the checkpoint's `checkpoint_digest` and the set) are kept in the cache
folder (train/config.default_cache_dir()). The output folder is written whole or not at all (the export's writer).

No `from __future__ import annotations` here: `RefitConfig` is loaded with Drake's `yaml_load_typed`, which reads the
fields' types."""

import hashlib
import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from trivla_drake.train import grounding_refit as refit
from trivla_drake.train import grounding_scenes as gs

TRAIN_SCENES_SEED = 0  # the scenes trained on
TEST_SCENES_SEED = 1  # the unseen scenes measured on: another seed
STATIC_CAMERA = "observation.images.static"
WRIST_CAMERA = "observation.images.wrist"


@dataclass
class RefitConfig:
    """Everything the re-fit depends on; the defaults are the shipped lineage's (models/trivla_cpu)."""

    # The checkpoint whose grounding read-out is re-fitted: a model folder (`load_checkpoint`) with an instruction
    # grounding.
    checkpoint: str = ""
    # The LeRobot dataset whose grounding frames fill half of every batch (the data the checkpoint was trained on),
    # with the static and wrist cameras and observation.tcp_pose.
    data: str = ""
    # The folder the re-fitted model is written to. An earlier export there is replaced once the new model is complete.
    out: str = ""
    # Replace `out` even when it holds other things than an earlier export (they are deleted; never the working folder).
    overwrite: bool = False
    # How many rendered grounding scenes to train on (drawn with seed TRAIN_SCENES_SEED).
    scenes: int = 12000
    # How many unseen rendered scenes (seed TEST_SCENES_SEED) to measure the sub-goal's error on, before and after.
    test_scenes: int = 600
    # Every `stride`-th grounding frame of `data` is used.
    stride: int = 3
    # Adam steps on the read-out (each batch: 32 rendered scenes and 32 dataset frames).
    steps: int = 1500
    # Adam's learning rate.
    lr: float = 3e-4
    # torch's CPU threads for the whole job (the numbers may depend on it: keep it to reproduce a model).
    threads: int = 2
    # The saved weights' dtype: float16 (half the size, as models/trivla_cpu), float32 or bfloat16.
    weights_dtype: str = "float16"
    # Keep System 2's Q_vl of every set in the cache folder and read it back on a later run of the same checkpoint.
    q_vl_cache: bool = True
    # Where to write the JSON report (errors before and after, loss curve, timings); None: beside `out`, as
    # OUT.refit.json.
    report: Optional[str] = None


def check_refit_config(config: RefitConfig) -> None:
    """ValueError naming the field of the first setting the job cannot run with."""
    from trivla_drake.nn.checkpoint import WEIGHT_DTYPES

    for name in ("checkpoint", "data", "out"):
        if not isinstance(getattr(config, name), str) or not getattr(config, name):
            raise ValueError(f"refit: {name} must name a folder; got {getattr(config, name)!r}")
    for name in ("checkpoint", "data"):
        if not Path(getattr(config, name)).is_dir():
            raise ValueError(f"refit: {name} {getattr(config, name)} is not a folder")
    for name in ("scenes", "test_scenes", "stride", "steps", "threads"):
        value = getattr(config, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"refit: {name} must be an integer >= 1; got {value!r}")
    if isinstance(config.lr, bool) or not isinstance(config.lr, (int, float)) or not (math.isfinite(config.lr)
                                                                                      and config.lr > 0):
        raise ValueError(f"refit: lr must be a finite number > 0; got {config.lr!r}")
    if config.weights_dtype not in WEIGHT_DTYPES:
        raise ValueError(f"refit: weights_dtype must be one of {', '.join(WEIGHT_DTYPES)}; got {config.weights_dtype!r}")
    if Path(report_path(config)).resolve().parent == Path(config.out).resolve():
        raise ValueError(f"refit: report {report_path(config)} lies in out {config.out}, which holds the model alone: "
                         "write it elsewhere")


def report_path(config: RefitConfig) -> str:
    """Where the job writes its report: `config.report`, or OUT.refit.json beside the model's folder."""
    out = Path(config.out)
    return config.report if config.report is not None else str(out.with_name(f"{out.name}.refit.json"))


def files_digest(folder: Path, pattern: str) -> str:
    """sha256 of the names and sha256s of `folder`'s files (not folders) matching `pattern`."""
    from trivla_drake.data.checksums import file_sha256

    digest = hashlib.sha256()
    for path in sorted(p for p in Path(folder).glob(pattern) if p.is_file()):
        digest.update(path.name.encode())
        digest.update(file_sha256(path).encode())
    return digest.hexdigest()


def cached_samples(checkpoint_digest: Optional[str], what: str, compute: Callable[[], refit.GroundingSamples], *,
                   progress: bool) -> refit.GroundingSamples:
    """`compute()`'s samples, kept in the cache folder under `what` and the checkpoint's digest (None: no cache)."""
    from trivla_drake.train.config import default_cache_dir

    if checkpoint_digest is None:
        return compute()
    key = hashlib.sha256(f"{checkpoint_digest}/{what}".encode()).hexdigest()[:16]
    path = Path(default_cache_dir()) / "grounding_q_vl" / f"{key}.pt"
    if path.is_file():
        if progress:
            print(f"Q_vl of {what} from {path}", flush=True)
        return refit.load_samples(path)
    samples = compute()
    refit.save_samples(samples, path)
    return samples


def rendered_samples(model, scenes: int, seed: int, checkpoint_digest: Optional[str], *,
                     progress: bool) -> refit.GroundingSamples:
    """Q_vl and labels of the rendered set of `scenes` scenes drawn with `seed` (rendered once into the cache folder)."""
    from trivla_drake.train.config import default_cache_dir

    settings = gs.grounding_scene_settings(scenes=scenes, seed=seed, image_size=model.image_size)
    key = gs.grounding_scene_key(settings)
    folder = Path(default_cache_dir()) / "grounding_scenes" / key
    return cached_samples(checkpoint_digest, f"scenes {key}", lambda: refit.scene_samples(
        model, gs.GroundingScenes(gs.ensure_grounding_scenes(folder, settings, progress=progress)), progress=progress),
        progress=progress)


def error_summaries(offsets: np.ndarray, tasks: list[str]) -> tuple[dict, dict]:
    """The sub-goal's median and 90th percentile x-y error [cm], and its median signed height error [cm] (sub-goal
    minus label), of all samples ("all") and of each task's, from the sub-goals' `offsets` [m] (N, 3) from their
    labels."""
    offsets, tasks = 100 * offsets, np.asarray(tasks)
    groups = {"all": np.ones(len(tasks), dtype=bool)} | {t: tasks == t for t in sorted(set(tasks.tolist()))}
    xy = np.linalg.norm(offsets[:, :2], axis=1)
    return ({k: [round(float(np.median(xy[rows])), 3), round(float(np.percentile(xy[rows], 90)), 3)]
             for k, rows in groups.items()},
            {k: round(float(np.median(offsets[rows, 2])), 3) for k, rows in groups.items()})


def run_refit(config: RefitConfig, *, progress: bool = True) -> dict:
    """Runs the re-fit `config` describes (module doc): writes the model to `config.out` and the report to
    `report_path(config)`; returns the report. ValueError naming the field for a setting it cannot run with, before
    any model loads. Sets torch's thread count to `config.threads` while it runs."""
    from trivla_drake.data.durable import atomic_write_text
    from trivla_drake.data.lerobot_reader import LeRobotReader
    from trivla_drake.nn import load_checkpoint
    from trivla_drake.nn.checkpoint import checkpoint_digest
    from trivla_drake.train.checkpoints import write_model_folder
    from trivla_drake.train.export_job import REFIT_CONFIG_FILE, check_out_folder

    check_refit_config(config)
    check_out_folder(config, flag="out", overwrite_flag="overwrite")
    threads = torch.get_num_threads()
    torch.set_num_threads(config.threads)
    try:
        model = load_checkpoint(config.checkpoint).eval()
        if model.policy.grounding is None:
            raise ValueError(f"refit: checkpoint {config.checkpoint} has no instruction grounding to re-fit")
        started = time.time()
        digest = checkpoint_digest(config.checkpoint) if config.q_vl_cache else None
        scenes = rendered_samples(model, config.scenes, TRAIN_SCENES_SEED, digest, progress=progress)
        tests = rendered_samples(model, config.test_scenes, TEST_SCENES_SEED, digest, progress=progress)
        scenes_s = time.time() - started
        frames = cached_samples(
            digest, f"frames {files_digest(Path(config.data) / 'meta', '*.json')} stride {config.stride}",
            lambda: refit.dataset_samples(model, LeRobotReader(config.data), stride=config.stride,
                                          static_camera=STATIC_CAMERA, wrist_camera=WRIST_CAMERA, progress=progress),
            progress=progress)
        prepare_s = time.time() - started
        sets = {"test_scenes": tests, "data_frames": frames}

        def errors() -> tuple[dict, dict]:
            """x-y errors of every set, height errors of the test scenes."""
            summaries = {name: error_summaries(refit.subgoal_offsets(model, s), s.tasks) for name, s in sets.items()}
            return ({name: xy for name, (xy, _) in summaries.items()},
                    {name: z for name, (_, z) in summaries.items() if name != "data_frames"})

        before, before_z = errors()
        curve = refit.refit_readout(model, scenes, frames, steps=config.steps, lr=config.lr, progress=progress)
        after, after_z = errors()
        write_model_folder(config.out, model, weights_dtype=config.weights_dtype,
                           job_config=(REFIT_CONFIG_FILE, config))
    finally:
        torch.set_num_threads(threads)
    report = {"config": asdict(config),
              "samples": {"scenes": len(scenes), "test_scenes": len(tests), "data_frames": len(frames)},
              "seconds": {"scenes_and_their_q_vl": round(scenes_s), "data_q_vl": round(prepare_s - scenes_s),
                          "refit": round(time.time() - started - prepare_s)},
              "median_and_p90_xy_error_cm": {"before": before, "after": after},
              "median_z_error_cm": {"before": before_z, "after": after_z},
              "loss_ema": [[step, loss] for step, loss in curve]}
    atomic_write_text(report_path(config), json.dumps(report, indent=1))
    return report
