"""How far the instruction grounding's sub-goal lies from its label on the frames System 1 trains on
(results/subgoal_trust/, run from the repository root):

    python results/subgoal_trust/grounding_on_training_frames.py CHECKPOINT DATA CARRY_TASKS [SAMPLES]

Builds the follow run's dataset from the feature cache (as `train --stage policy --feature-stride 3
--vl-position-embedding --grounding-weight 1 --grounding-phase follow --grounding-carry CARRY_TASKS
--subgoal-offset` does), draws SAMPLES frames (default 3000, seed 0) and prints the median and 90th percentile of the sub-goal's x-y error, and the
median height error, on the grounding's own frames (before the first gripper change, and the carrying frames of
the --grounding-carry tasks) and on the rest."""
import argparse
import dataclasses
import sys

import numpy as np
import torch

from trivla_drake.data.lerobot import LeRobotReader
from trivla_drake.nn.panda_tcp import denormalize_position
from trivla_drake.train import trainer
from trivla_drake.train.cli_commands import add_train_parser, config_from_args
from trivla_drake.train.config import default_cache_dir
from trivla_drake.train.distributed import DistEnv


def main(checkpoint: str, data: str, carry: str, samples: int) -> None:
    torch.set_num_threads(2)
    parser = argparse.ArgumentParser()
    add_train_parser(parser.add_subparsers())
    args = parser.parse_args(["train", "--stage", "policy", "--feature-stride", "3", "--vl-position-embedding",
                              "--grounding-weight", "1", "--data", data, "--out", "unused", "--init", checkpoint,
                              "--grounding-phase", "follow", "--grounding-carry", carry, "--subgoal-offset"])
    config = config_from_args(args)
    config = dataclasses.replace(config, preset=trainer._resolve_preset(config),
                                 cache_dir=config.cache_dir or default_cache_dir())
    model = trainer.build_model(config, None).eval()
    dataset, collate, _ = trainer._prepare_data(config, model, LeRobotReader(data), DistEnv())
    rows = np.random.default_rng(0).choice(len(dataset), size=min(samples, len(dataset)), replace=False)
    xy, dz, own = [], [], []
    with torch.no_grad():
        for start in range(0, len(rows), 64):
            batch = collate([dataset[int(i)] for i in rows[start:start + 64]])
            subgoal = model.subgoal_of_features(batch["q_vl"].float(), batch.get("q_vl_mask"), batch["state"].float())
            predicted = denormalize_position(subgoal[:, :3])
            error = predicted - batch["subgoal_position"]
            xy.append(error[:, :2].norm(dim=1).numpy())
            dz.append(error[:, 2].abs().numpy())
            own.append(batch["subgoal_in_loss"].numpy())
    xy, dz, own = np.concatenate(xy), np.concatenate(dz), np.concatenate(own)
    print(f"{checkpoint} on {len(rows)} frames of {len(dataset)} ({data}, stride 3)")
    print("| frames | n | median x-y error | 90th percentile | median height error |\n| --- | --- | --- | --- | --- |")
    for name, chosen in (("the grounding's own (approach, carrying)", own), ("the rest", ~own),
                         ("all", np.ones_like(own))):
        print(f"| {name} | {chosen.sum()} | {100 * np.median(xy[chosen]):.2f} cm | "
              f"{100 * np.percentile(xy[chosen], 90):.2f} cm | {100 * np.median(dz[chosen]):.2f} cm |")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]) if len(sys.argv) > 4 else 3000)
