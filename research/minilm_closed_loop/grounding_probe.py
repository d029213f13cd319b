"""Where does System 1's instruction grounding send the hand when the instruction is a held-out paraphrase?

For every clean demonstration's first frame (a scene the model was trained on, so only the wording is new), each
model's grounding predicts the next gripper event's tool-centre-point position (`TriVLA.predict_subgoal`) from the
episode's own training instruction and from each of its task's held-out paraphrases filled with the same colours.
The error is the distance to where the oracle's gripper next changed (data/subgoals.py). A grounding that
understands a paraphrase puts it where the template puts it.

    python research/minilm_closed_loop/grounding_probe.py --data minilm_closed_loop_run/data \
        --models A=minilm_closed_loop_run/runs/a_export B=minilm_closed_loop_run/runs/b_export
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.data.samples import GRIPPER_INDEX
from trivla_drake.data.subgoals import next_gripper_event_positions
from trivla_drake.eval.model_loading import load_model
from trivla_drake.tasks.suite import TASKS

NEAR_M = 0.05


def first_frames(data: str, per_task: int) -> list[dict]:
    """The first frame of the first `per_task` unperturbed episodes of each task: images, state, label."""
    reader = LeRobotReader(data)
    taken: dict[str, int] = {}
    frames = []
    for index in range(reader.num_episodes):
        row = reader.episodes[index]
        task = row["trivla/task"]
        if row.get("trivla/action_noise") or row.get("trivla/perturbed_frames") or row.get("trivla/prelude"):
            continue
        if taken.get(task, 0) >= per_task:
            continue
        taken[task] = taken.get(task, 0) + 1
        columns = reader.episode_frames(index)
        label = next_gripper_event_positions(columns["action"][:, GRIPPER_INDEX], columns["observation.tcp_pose"][:, :3])[0]
        frames.append({"task": task, "params": tuple(row["trivla/params"]), "template": row["tasks"][0],
                       "static": reader.episode_video(index, "observation.images.static")[0],
                       "wrist": reader.episode_video(index, "observation.images.wrist")[0],
                       "state": columns["observation.state"][0].astype(np.float64), "label": label.astype(np.float64)})
    return frames


def probe(model, frames: list[dict]) -> list[dict]:
    """Per frame: the template's error and each paraphrase's error [m]."""
    rows = []
    for frame in frames:
        task = TASKS[frame["task"]]
        params = frame["params"]

        def subgoal(text: str) -> np.ndarray:
            return model.predict_subgoal(frame["static"], frame["wrist"], text, frame["state"])

        at_template = subgoal(frame["template"])
        paraphrases = [p.format(color=params[0] if params else "", other=params[1] if len(params) > 1 else "")
                       for p in task.paraphrases]
        at_paraphrases = [subgoal(text) for text in paraphrases]
        rows.append({"task": frame["task"],
                     "template_error": float(np.linalg.norm(at_template - frame["label"])),
                     "paraphrase_errors": [float(np.linalg.norm(p - frame["label"])) for p in at_paraphrases]})
    return rows


def summary(rows: list[dict]) -> dict:
    template = np.array([r["template_error"] for r in rows])
    paraphrase = np.array([e for r in rows for e in r["paraphrase_errors"]])
    near = float(np.mean(paraphrase < NEAR_M))
    return {"frames": len(rows), "paraphrases": len(paraphrase),
            "template_median_cm": 100 * float(np.median(template)),
            "paraphrase_median_cm": 100 * float(np.median(paraphrase)),
            "template_near": float(np.mean(template < NEAR_M)), "paraphrase_near": near,
            "paraphrase_near_stderr": float(np.sqrt(near * (1 - near) / len(paraphrase)))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--models", nargs="+", required=True, metavar="NAME=CHECKPOINT")
    parser.add_argument("--per-task", type=int, default=10)
    parser.add_argument("--pairs", nargs="*", metavar="X-Y", default=None,
                        help="paired differences to print, e.g. B-A (default: each model minus the one before it)")
    parser.add_argument("--out", default="research/minilm_closed_loop/grounding_probe.json")
    args = parser.parse_args()
    torch.set_num_threads(2)
    frames = first_frames(args.data, args.per_task)
    report, rows_of = {}, {}
    print(f"{len(frames)} first frames; near: within {100 * NEAR_M:.0f} cm of the oracle's next gripper event")
    print("| model | template: median error, near | paraphrases: median error, near |")
    print("| --- | --- | --- |")
    for spec in args.models:
        name, checkpoint = spec.split("=", 1)
        rows = rows_of[name] = probe(load_model(checkpoint), frames)
        s = summary(rows)
        per_task = {task: summary([r for r in rows if r["task"] == task]) for task in sorted({r["task"] for r in rows})}
        report[name] = {"checkpoint": checkpoint, **s, "paraphrase_near_per_frame": near_per_frame(rows).tolist(),
                        "per_task": per_task}
        print(f"| {name} | {s['template_median_cm']:.1f} cm, {s['template_near']:.2f} | "
              f"{s['paraphrase_median_cm']:.1f} cm, {s['paraphrase_near']:.2f} ± {s['paraphrase_near_stderr']:.2f} |")
    names = list(report)
    print("\nparaphrases near, paired by frame (each frame's paraphrases averaged), per task and in all:")
    print("| task | " + " | ".join(names) + " |")
    print("| --- |" + " --- |" * len(names))
    for task in sorted(report[names[0]]["per_task"]):
        print(f"| {task} | " + " | ".join(f"{report[n]['per_task'][task]['paraphrase_near']:.2f}" for n in names) + " |")
    pairs = [pair.split("-", 1)[::-1] for pair in args.pairs] if args.pairs is not None else zip(names, names[1:])
    for first, second in pairs:
        d = near_per_frame(rows_of[second]) - near_per_frame(rows_of[first])
        report[f"{second}_minus_{first}_paraphrase_near"] = [float(d.mean()), float(d.std(ddof=1) / np.sqrt(len(d)))]
        print(f"{second} - {first}: {d.mean():+.3f} ± {d.std(ddof=1) / np.sqrt(len(d)):.3f} over {len(d)} frames")
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")


def near_per_frame(rows: list[dict]) -> np.ndarray:
    """Per frame, the share of its paraphrases whose sub-goal is within NEAR_M of the label."""
    return np.array([np.mean(np.array(r["paraphrase_errors"]) < NEAR_M) for r in rows])


if __name__ == "__main__":
    main()
