"""Reproduce step 46 (run from the repository root): re-fits a checkpoint's instruction-grounding read-out on
rendered grounding scenes mixed with a dataset's grounding frames (trivla_drake/train/grounding_refit.py), measures
the sub-goal's x-y error on unseen rendered scenes before and after, and saves the model in float16 (as the default
checkpoint). Writes OUT/ (the checkpoint), REPORT.json (errors per task, loss curve, timings) and REPORT.loss.png
(REPORT: --report, default OUT).

python results/grounding_scenes/refit_grounding.py CHECKPOINT DATA OUT [--scenes 12000] [--test-scenes 600]
    [--chain-starts 0] [--stacked-picks 0] [--stacked-share F] [--hold W] [--goal-hold W] [--steps 1500] [--lr 3e-4] [--stride 3]
    [--threads 2] [--report PREFIX] [--no-q-vl-cache]

With --chain-starts F, that fraction of the training scenes start where one or two earlier tasks of a chain left
the scene and the arm (train/grounding_scenes.py), and the errors are also reported on 600 unseen scenes that all
start so (`test_chain_starts`). With --stacked-picks F, that fraction of the lift, place in bowl and stack scenes
pick the top block of a stack (results/stacked_subgoal/), and the errors are also reported on 600 unseen scenes whose
lift, place in bowl and stack all do (`test_stacked_picks`). Every test set also reports the sub-goal's median
height error (`median_z_error_cm`, signed: sub-goal minus label). --stacked-share F draws that fraction of each
batch's scenes from the stacked picks, --hold W pulls every other sample toward the sub-goal the read-out gave it
before and --goal-hold W toward the goal token it gave System 1 (grounding_refit.refit_readout; results/stacked_hold/).
The report also has how far the goal token moved (`median_goal_drift`: |after - before| / |before|, per task).

System 2's Q_vl of every set is computed once per checkpoint and kept in the cache folder
(train/config.default_cache_dir()/grounding_q_vl, keyed by the checkpoint's files and the set), so a second re-fit of
the same checkpoint starts training at once; --no-q-vl-cache computes them anew and keeps nothing."""
import argparse
import hashlib
import json
import time
from pathlib import Path

import numpy as np
import torch

from trivla_drake.data.lerobot import LeRobotReader
from trivla_drake.nn import load_checkpoint
from trivla_drake.nn.checkpoint import save_checkpoint
from trivla_drake.train import grounding_refit as refit
from trivla_drake.train import grounding_scenes as gs
from trivla_drake.train.config import default_cache_dir

TRAIN_SEED, TEST_SEED = 0, 1  # the unseen test scenes are drawn with another seed


def by_task(values: np.ndarray, samples) -> dict[str, np.ndarray]:
    """`values` (one per sample) for all samples and for each task's."""
    tasks = np.asarray(samples.tasks)
    return {"all": values} | {t: values[tasks == t] for t in sorted(set(samples.tasks))}


def error_summaries(offsets: np.ndarray, samples) -> tuple[dict, dict]:
    """The sub-goal's median and 90th percentile x-y error [cm], and its median signed height error [cm] (sub-goal
    minus label), all samples and per task, from the sub-goals' `offsets` [m] (N, 3) from their labels."""
    offsets = 100 * offsets
    xy = by_task(np.linalg.norm(offsets[:, :2], axis=1), samples)
    z = by_task(offsets[:, 2], samples)
    return ({k: [round(float(np.median(v)), 3), round(float(np.percentile(v, 90)), 3)] for k, v in xy.items()},
            {k: round(float(np.median(v)), 3) for k, v in z.items()})


def files_digest(folder: Path, pattern: str) -> str:
    """sha256 of the names and bytes of `folder`'s files matching `pattern`."""
    digest = hashlib.sha256()
    for path in sorted(Path(folder).glob(pattern)):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def q_vl_cached(checkpoint_digest: str | None, what: str, compute):
    """`compute()`'s samples, kept under the cache folder by `what` and the checkpoint's digest (None: no cache)."""
    if checkpoint_digest is None:
        return compute()
    key = hashlib.sha256(f"{checkpoint_digest}/{what}".encode()).hexdigest()[:16]
    path = Path(default_cache_dir()) / "grounding_q_vl" / f"{key}.pt"
    if path.is_file():
        print(f"Q_vl of {what} from {path}", flush=True)
        return refit.load_samples(path)
    samples = compute()
    refit.save_samples(samples, path)
    return samples


def rendered(model, scenes: int, seed: int, chain_starts: float = 0.0, stacked_picks: float = 0.0,
             checkpoint_digest: str | None = None):
    settings = gs.grounding_scene_settings(scenes=scenes, seed=seed, image_size=model.image_size,
                                           chain_starts=chain_starts, stacked_picks=stacked_picks)
    key = gs.grounding_scene_key(settings)
    folder = Path(default_cache_dir()) / "grounding_scenes" / key
    return q_vl_cached(checkpoint_digest, f"scenes {key}", lambda: refit.scene_samples(
        model, gs.GroundingScenes(gs.ensure_grounding_scenes(folder, settings))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint")
    parser.add_argument("data")
    parser.add_argument("out")
    parser.add_argument("--scenes", type=int, default=12000)
    parser.add_argument("--test-scenes", type=int, default=600)
    parser.add_argument("--chain-starts", type=float, default=0.0,
                        help="fraction of the training scenes that start where a chain's earlier tasks left them")
    parser.add_argument("--stacked-picks", type=float, default=0.0,
                        help="fraction of the lift, place in bowl and stack scenes that pick the top block of a stack")
    parser.add_argument("--stacked-share", type=float, default=None,
                        help="fraction of each batch's scenes drawn from the stacked picks (default: uniform)")
    parser.add_argument("--hold", type=float, default=0.0,
                        help="weight pulling every sample that picks no stacked block toward its sub-goal before")
    parser.add_argument("--goal-hold", type=float, default=0.0,
                        help="weight pulling the goal token System 1 reads toward where it was, on the same samples")
    parser.add_argument("--no-q-vl-cache", action="store_true", help="compute System 2's Q_vl anew, keep nothing")
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--stride", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--report", default=None, help="prefix of the report's .json and .loss.png (default: OUT)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model = load_checkpoint(args.checkpoint).eval()
    if model.policy.grounding is None:
        raise SystemExit(f"{args.checkpoint} has no instruction grounding to re-fit")
    started = time.time()
    digest = None if args.no_q_vl_cache else files_digest(Path(args.checkpoint), "*")
    scenes = rendered(model, args.scenes, TRAIN_SEED, args.chain_starts, args.stacked_picks, digest)
    tests = {"test_scenes": rendered(model, args.test_scenes, TEST_SEED, checkpoint_digest=digest)}
    if args.chain_starts > 0:
        tests["test_chain_starts"] = rendered(model, args.test_scenes, TEST_SEED, 1.0, checkpoint_digest=digest)
    if args.stacked_picks > 0:
        tests["test_stacked_picks"] = rendered(model, args.test_scenes, TEST_SEED, stacked_picks=1.0,
                                               checkpoint_digest=digest)
    scenes_s = time.time() - started
    data_key = f"frames {files_digest(Path(args.data) / 'meta', '*.json')} stride {args.stride}"
    frames = q_vl_cached(digest, data_key, lambda: refit.dataset_samples(
        model, LeRobotReader(args.data), stride=args.stride,
        static_camera="observation.images.static", wrist_camera="observation.images.wrist"))
    prepare_s = time.time() - started
    sets = tests | {"data_frames": frames}

    def outputs():
        """One pass of the grounding over every set: its goal tokens and its sub-goals' offsets [m] from the labels."""
        out = {}
        for name, samples in sets.items():
            goals, raw = refit.grounding_outputs(model, samples)
            out[name] = (goals, refit.offsets_from_raw(raw, samples))
        return out

    def errors(out):
        """x-y errors of the test sets and the data frames; height errors of the test sets."""
        summaries = {name: error_summaries(offsets, sets[name]) for name, (_, offsets) in out.items()}
        return ({name: xy for name, (xy, _) in summaries.items()},
                {name: z for name, (_, z) in summaries.items() if name != "data_frames"})

    outputs_before = outputs()
    before, before_z = errors(outputs_before)
    print("before", json.dumps({k: v["all"] for k, v in before.items()}), flush=True)
    curve = refit.refit_readout(model, scenes, frames, steps=args.steps, lr=args.lr,
                                stacked_share=args.stacked_share, hold_weight=args.hold, goal_hold_weight=args.goal_hold)
    outputs_after = outputs()
    after, after_z = errors(outputs_after)
    drift = {}  # how far the goal token System 1 reads moved, relative, median per task
    for name, samples in sets.items():
        moved = by_task(refit.goal_drift(outputs_before[name][0], outputs_after[name][0]).numpy(), samples)
        drift[name] = {k: round(float(np.median(v)), 3) for k, v in moved.items()}
    print("goal drift", json.dumps({k: v["all"] for k, v in drift.items()}), flush=True)
    print("after", json.dumps({k: v["all"] for k, v in after.items()}), flush=True)
    save_checkpoint(model, args.out, weights_dtype="float16")
    report = {"checkpoint": args.checkpoint, "data": args.data, "settings": vars(args),
              "samples": {"scenes": len(scenes), "data_frames": len(frames)} | {k: len(v) for k, v in tests.items()},
              "seconds": {"scenes_and_their_q_vl": round(scenes_s), "data_q_vl": round(prepare_s - scenes_s),
                          "refit": round(time.time() - started - prepare_s)},
              "median_and_p90_xy_error_cm": {"before": before, "after": after},
              "median_z_error_cm": {"before": before_z, "after": after_z}, "median_goal_drift": drift,
              "loss_ema": curve}
    report_prefix = args.report or args.out
    Path(f"{report_prefix}.json").write_text(json.dumps(report, indent=1))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2))
    ax.plot(*zip(*curve))
    ax.set(xlabel="step", ylabel="grounding loss (EMA)", yscale="log", title="re-fit on rendered grounding scenes")
    fig.tight_layout()
    fig.savefig(f"{report_prefix}.loss.png", dpi=120)


if __name__ == "__main__":
    main()
