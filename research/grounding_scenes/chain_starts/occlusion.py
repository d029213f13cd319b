"""Where the grounding misses on chain-start scenes: its sub-goal's x-y error against how much of the block to grasp
the static camera sees (run from the repository root; session 45).

python results/grounding_scenes/chain_starts/occlusion.py OUT.json LABEL=CHECKPOINT [LABEL=CHECKPOINT ...]
    [--scenes 600] [--seed 1] [--threads 2]

Renders (or reuses from the training cache) the unseen chain-start scenes that `refit_grounding.py --chain-starts`
tests on (every scene a chain start, seed 1), counts the pixels of the block the instruction names first (the block
to grasp) in each camera's label image, and prints each model's median and 90th-percentile error by that count.
OUT.json holds the counts and every scene's error per model."""
import argparse
import json
from pathlib import Path

import numpy as np
import torch

from trivla_drake.nn import load_checkpoint
from trivla_drake.robot.panda_kinematics import PandaKinematics
from trivla_drake.tasks.scene import BLOCK_COLORS
from trivla_drake.train import grounding_refit as refit
from trivla_drake.train import grounding_scenes as gs
from trivla_drake.train.config import default_cache_dir
from trivla_drake.train.vqa import SceneRenderer

BINS = ((0, 1), (1, 50), (50, 150), (150, None))  # static-view pixels of the block to grasp (224 x 224 image)


def first_color(instruction: str) -> str:
    """The colour the instruction names first: the block a grasp-first task picks up."""
    return min((c for c in BLOCK_COLORS if c in instruction), key=instruction.index)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out")
    parser.add_argument("models", nargs="+", help="LABEL=CHECKPOINT")
    parser.add_argument("--scenes", type=int, default=600)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    models = dict(spec.split("=", 1) for spec in args.models)
    first = load_checkpoint(next(iter(models.values())))
    settings = gs.grounding_scene_settings(scenes=args.scenes, seed=args.seed, image_size=first.image_size,
                                           chain_starts=1.0)
    folder = Path(default_cache_dir()) / "grounding_scenes" / gs.grounding_scene_key(settings)
    scenes = gs.GroundingScenes(gs.ensure_grounding_scenes(folder, settings))
    renderer, kinematics = SceneRenderer(first.image_size), PandaKinematics()
    layout = renderer.layout()
    pixels = []
    for i in range(len(scenes)):  # the same draws as the set's: its specs, rendered again for their label images
        scene = gs.sample_grounding_scene(i, args.seed, layout, kinematics, 1.0)
        renderer.render(scene["spec"])
        label = 1 + BLOCK_COLORS.index(first_color(scene["instruction"]))
        pixels.append([int((view == label).sum()) for view in renderer.block_labels()])
    pixels = np.asarray(pixels)
    report = {"scenes": str(folder), "static_pixels": pixels[:, 0].tolist(), "wrist_pixels": pixels[:, 1].tolist(),
              "tasks": scenes.tasks, "along_approach": scenes.along_approach.tolist(), "error_cm": {}}
    for label, checkpoint in models.items():
        model = load_checkpoint(checkpoint).eval()
        report["error_cm"][label] = (100 * refit.subgoal_errors(model, refit.scene_samples(model, scenes))).round(3).tolist()
    Path(args.out).write_text(json.dumps(report))
    print("| static-view pixels of the block | scenes | " + " | ".join(f"{m}: median / p90 [cm]" for m in models) + " |")
    print("| --- | --- |" + " --- |" * len(models))
    for low, high in BINS:
        rows = (pixels[:, 0] >= low) & (pixels[:, 0] < (high if high is not None else np.inf))
        cells = [f"{np.median(np.asarray(e)[rows]):.2f} / {np.percentile(np.asarray(e)[rows], 90):.2f}" if rows.any()
                 else "-" for e in report["error_cm"].values()]
        print(f"| {low}-{high if high is not None else ''} | {int(rows.sum())} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
