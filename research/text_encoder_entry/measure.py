"""Where should the frozen MiniLM enter (issue 77)? After each system's own training stage, does a held-out
paraphrase's task survive into what System 1 reads from that system: System 2's Q_vl (its instruction tokens, the
middle-layer states) and System 3's F_p (the up-sampling features of both cameras)?

For each of a few real scenes (the first frame of collected episodes, both cameras) and each model, the 36 training
templates and the 36 held-out paraphrases are run through System 2 (Q_vl, mean over the positions from the
instruction's first token on: the instruction and the prompt's tail) and
System 3 (F_p of both views flattened, one fixed noise draw, the mean over the 72 sentences taken off so that the
scene cancels); a paraphrase is a hit when its nearest template by cosine belongs to its own task. The gap is the
mean similarity to its own task's templates minus that to other tasks'. Hits are summed over the scenes.

    python research/text_encoder_entry/measure.py --data trivla_next_run/data/next \
        --system2 models/trivla_cpu trivla_next_run/runs/vlm/final \
        --system3 models/trivla_cpu trivla_next_run/runs/video/final        # writes figures.json beside it
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.nn import load_checkpoint
from trivla_drake.tasks.suite import TASKS

STATIC, WRIST = "observation.images.static", "observation.images.wrist"


def sentences() -> tuple[list[str], list[str], list[tuple[str, str]]]:
    """Owners of the templates, the templates, and (task, paraphrase) pairs, colours filled as red / blue."""
    def fill(text):
        return text.format(color="red", other="blue")

    owners = [name for name, task in TASKS.items() for _ in task.templates]
    templates = [fill(t) for task in TASKS.values() for t in task.templates]
    paraphrases = [(name, fill(p)) for name, task in TASKS.items() for p in task.paraphrases]
    return owners, templates, paraphrases


def score(template_vectors: torch.Tensor, paraphrase_vectors: torch.Tensor) -> dict:
    owners, _, paraphrases = sentences()
    similarity = F.normalize(paraphrase_vectors, dim=-1) @ F.normalize(template_vectors, dim=-1).T
    own = torch.tensor([[owner == name for owner in owners] for name, _ in paraphrases])
    hits = sum(owners[int(j)] == name for (name, _), j in zip(paraphrases, similarity.argmax(1)))
    return {"hits": int(hits), "of": len(paraphrases),
            "gap": float(similarity[own].mean() - similarity[~own].mean())}


def scenes(data: str, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The first frame of `count` episodes spread over the dataset (both cameras)."""
    reader = LeRobotReader(data)
    picks = np.linspace(0, reader.num_episodes - 1, count).astype(int)
    return [(reader.episode_video(int(i), STATIC)[0], reader.episode_video(int(i), WRIST)[0]) for i in picks]


@torch.no_grad()
def system2_vectors(model, static: np.ndarray, wrist: np.ndarray, texts: list[str]) -> torch.Tensor:
    vl = model.vision_language
    offset = vl.instruction_offset(2)
    n = len(texts)
    q_vl, mask = model.encode_vision_language_batch(torch.from_numpy(np.stack([static] * n)),
                                                    torch.from_numpy(np.stack([wrist] * n)), texts)
    keep = mask.clone().float()
    keep[:, :offset] = 0
    return (q_vl * keep[..., None]).sum(1) / keep.sum(1, keepdim=True)


@torch.no_grad()
def system3_vectors(model, static: np.ndarray, wrist: np.ndarray, texts: list[str]) -> torch.Tensor:
    rows = []
    for text in texts:  # one fixed noise draw per sentence: the text is all that differs
        generator = torch.Generator().manual_seed(0)
        f_static, f_wrist = model.encode_dynamics_batch(torch.from_numpy(static[None]), torch.from_numpy(wrist[None]),
                                                        [text], generator=generator)
        rows.append(torch.cat([f_static.flatten(), f_wrist.flatten()]))
    vectors = torch.stack(rows)
    return vectors - vectors.mean(0, keepdim=True)


def measure(checkpoint: str, system: int, views: list[tuple[np.ndarray, np.ndarray]]) -> dict:
    model = load_checkpoint(checkpoint).eval()
    _, templates, paraphrases = sentences()
    texts = templates + [text for _, text in paraphrases]
    embed = system2_vectors if system == 2 else system3_vectors
    per_scene = []
    for static, wrist in views:
        vectors = embed(model, static, wrist, texts)
        per_scene.append(score(vectors[:len(templates)], vectors[len(templates):]))
    return {"checkpoint": checkpoint, "text_encoder": model.config.text_encoder,
            "hits": sum(s["hits"] for s in per_scene), "of": sum(s["of"] for s in per_scene),
            "gap": float(np.mean([s["gap"] for s in per_scene])), "per_scene": per_scene}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="a collected dataset (its episodes' first frames are the scenes)")
    parser.add_argument("--scenes", type=int, default=4)
    parser.add_argument("--system2", nargs="*", default=[], help="checkpoints whose System 2 is measured")
    parser.add_argument("--system3", nargs="*", default=[], help="checkpoints whose System 3 is measured")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    views = scenes(args.data, args.scenes)
    figures = {"scenes": args.scenes, "system2": [measure(c, 2, views) for c in args.system2],
               "system3": [measure(c, 3, views) for c in args.system3]}
    print("| system | checkpoint | text encoder | paraphrases nearest their own task's template, per scene | "
          "similarity gap |")
    print("| --- | --- | --- | --- | --- |")
    for system in ("system2", "system3"):
        for row in figures[system]:
            hits = [scene["hits"] for scene in row["per_scene"]]
            print(f"| {system} | {row['checkpoint']} | {row['text_encoder'] or 'from scratch'} | "
                  f"{', '.join(map(str, hits))} of {row['per_scene'][0]['of']} | {row['gap']:.3f} |")
    (Path(__file__).parent / "figures.json").write_text(json.dumps(figures, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
