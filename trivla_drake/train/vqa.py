"""Vision-language data for System 2, generated from the simulator's ground truth (nothing downloaded).

Scenes are sampled like the task suite's (`sample_scene`), sometimes with blocks put in the bowl,
written into a station with `StationHandles.apply`, rendered by both cameras, and read back as a
`SceneState`; questions and answers are written from that state: block colours and positions,
spatial relations, stacks, the bowl, the drawer (open/closed), the lamp (on/off), counts, and a
scene caption. Positions are in the robot's frame ("left" is +y, the robot's left, as in the task
instructions); a question whose answer would be within a few centimetres of a boundary is not asked.

The set is written once to a folder (atomically: a temporary folder renamed into place):
    meta.json    settings, counts, the held-out scenes
    static.npy   uint8 (scenes, S, S, 3)      wrist.npy   uint8 (scenes, S, S, 3)
    labels.npy   uint8 (scenes, 2, S, S): what each pixel of the static / wrist view shows, from the
                 renderer's label image: 0 anything else, 1 + i the block BLOCK_COLORS[i]
    qa.parquet   scene, question, answer, kind, answer_type, split ("train" / "eval")
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from trivla_drake.train.atomic_folder import atomic_folder, ensure_cached_folder

from trivla_drake.tasks.scene import (
    BLOCK_COLORS,
    BLOCK_HALF,
    BlockPlacement,
    Layout,
    SceneSpec,
    SceneState,
    sample_scene,
)

VQA_FORMAT_VERSION = 2  # 2: labels.npy
EVAL_EVERY = 10  # every 10th scene is held out for evaluation

# Position bands [m] in the robot frame over the work area (x away from the robot, y to its left),
# and how far from a band edge a block must be for its band to be stated.
DEPTH_EDGES = (0.42, 0.50)  # near | middle | far
SIDE_EDGES = (-0.035, 0.065)  # right | centre | left
BAND_MARGIN = 0.01
RELATION_MARGIN = 0.03  # a pairwise relation is asked only when the blocks differ by this much
DRAWER_OPEN_MIN = 0.05  # [m] an opening above this is "open" (sampled scenes: 0 or 0.11-0.14)
BOWL_FLOOR = 0.008  # top of the bowl's base [m] (models/bowl.sdf)
NUMBER_WORDS = ("zero", "one", "two", "three")
ANSWER_SETS: dict[str, tuple[str, ...]] = {
    "yes_no": ("yes", "no"),
    "color": BLOCK_COLORS + ("none",),
    "drawer": ("open", "closed"),
    "lamp": ("on", "off"),
    "count": NUMBER_WORDS,
}
"""Closed answer sets (used to score held-out questions by likelihood); other answers are free text."""


@dataclass(frozen=True)
class VQAItem:
    """One question about a scene with its ground-truth answer."""

    question: str
    answer: str
    kind: str  # what is asked about: caption, where, relation, superlative, bowl, stack, count, drawer, lamp
    answer_type: str  # a key of ANSWER_SETS, or "free"


# ---------------------------------------------------------------------------------------------
# Ground truth -> words


def _band(value: float, edges: tuple[float, float], names: tuple[str, str, str]) -> str | None:
    if any(abs(value - e) < BAND_MARGIN for e in edges):
        return None
    return names[0] if value < edges[0] else names[1] if value < edges[1] else names[2]


def depth_phrase(x: float) -> str | None:
    """'near the robot' / 'in the middle of the table' / 'far from the robot', None near a band edge."""
    return _band(x, DEPTH_EDGES, ("near the robot", "in the middle of the table", "far from the robot"))


def side_phrase(y: float) -> str | None:
    """'on the right' / 'in the centre' / 'on the left' (the robot's), None near a band edge."""
    return _band(y, SIDE_EDGES, ("on the right", "in the centre", "on the left"))


def block_place(scene: SceneState, color: str) -> str:
    """Where a block is, in words: in the bowl, on top of another block, or on the table (with the
    position bands that are unambiguous)."""
    if scene.in_bowl(color):
        return "in the bowl"
    base = scene.base_of(color)
    if base is not None:
        return f"on top of the {base} block"
    x, y = scene.block_position(color)[:2]
    parts = [p for p in (depth_phrase(x), side_phrase(y)) if p]
    return "on the table" + (", " + ", ".join(parts) if parts else "")


def scene_caption(scene: SceneState) -> str:
    """A caption naming every block's place, the drawer and the lamp."""
    sentences = [f"The {c} block is {block_place(scene, c)}." for c in BLOCK_COLORS if c in scene.blocks]
    sentences.append(f"The drawer is {'open' if scene.drawer_opening > DRAWER_OPEN_MIN else 'closed'}.")
    sentences.append(f"The lamp is {'on' if scene.lamp_on else 'off'}.")
    return " ".join(sentences)


def _yes_no(flag: bool) -> str:
    return "yes" if flag else "no"


def question_pool(scene: SceneState) -> dict[str, list[VQAItem]]:
    """Every question this module can ask about `scene` whose answer is unambiguous, by kind."""
    colors = [c for c in BLOCK_COLORS if c in scene.blocks]
    xy = {c: scene.block_position(c)[:2] for c in colors}
    reach = {c: float(np.hypot(*xy[c])) for c in colors}  # distance from the robot's base
    pool: dict[str, list[VQAItem]] = {k: [] for k in
                                      ("caption", "where", "relation", "superlative", "bowl", "stack", "count",
                                       "drawer", "lamp")}
    add = lambda kind, q, a, t: pool[kind].append(VQAItem(q, a, kind, t))  # noqa: E731

    for q in ("describe the scene.", "what do you see on the table?"):
        add("caption", q, scene_caption(scene), "free")
    for c in colors:
        add("where", f"where is the {c} block?", block_place(scene, c), "free")

    for a in colors:
        for b in colors:
            if a == b:
                continue
            dy = xy[a][1] - xy[b][1]
            if abs(dy) >= RELATION_MARGIN:
                add("relation", f"is the {a} block to the left of the {b} block?", _yes_no(dy > 0), "yes_no")
                add("relation", f"is the {a} block to the right of the {b} block?", _yes_no(dy < 0), "yes_no")
            dr = reach[a] - reach[b]
            if abs(dr) >= RELATION_MARGIN:
                add("relation", f"is the {a} block closer to the robot than the {b} block?", _yes_no(dr < 0), "yes_no")

    def extreme(values: dict[str, float], question: str, largest: bool) -> None:
        order = sorted(values, key=values.get, reverse=largest)
        if len(order) >= 2 and abs(values[order[0]] - values[order[1]]) >= RELATION_MARGIN:
            add("superlative", question, order[0], "color")

    extreme({c: float(xy[c][1]) for c in colors}, "which block is furthest to the left?", True)
    extreme({c: float(xy[c][1]) for c in colors}, "which block is furthest to the right?", False)
    extreme(reach, "which block is closest to the robot?", False)
    extreme(reach, "which block is furthest from the robot?", True)
    bowl_xy = scene.layout.bowl[:2, 3]
    extreme({c: float(np.linalg.norm(xy[c] - bowl_xy)) for c in colors}, "which block is closest to the bowl?", False)

    in_bowl = [c for c in colors if scene.in_bowl(c)]
    for c in colors:
        add("bowl", f"is the {c} block in the bowl?", _yes_no(c in in_bowl), "yes_no")
    add("count", "how many blocks are in the bowl?", NUMBER_WORDS[len(in_bowl)], "count")
    on_table = [c for c in colors if scene.on_table(c)]
    add("count", "how many blocks are on the table?", NUMBER_WORDS[len(on_table)], "count")
    if len(in_bowl) == 1:
        add("bowl", "what colour is the block in the bowl?", in_bowl[0], "color")

    tops = [c for c in colors if scene.base_of(c) is not None]
    add("stack", "which block is on top of another block?", tops[0] if len(tops) == 1 else "none", "color")
    for a in colors:
        for b in colors:
            if a != b:
                add("stack", f"is the {a} block stacked on the {b} block?", _yes_no(scene.stacked_on(a, b)), "yes_no")
    for top in tops:
        add("stack", f"what colour is the block under the {top} block?", scene.base_of(top), "color")

    is_open = scene.drawer_opening > DRAWER_OPEN_MIN
    add("drawer", "is the drawer open or closed?", "open" if is_open else "closed", "drawer")
    add("drawer", "is the drawer open?", _yes_no(is_open), "yes_no")
    add("drawer", "is the drawer closed?", _yes_no(not is_open), "yes_no")
    add("lamp", "is the lamp on or off?", "on" if scene.lamp_on else "off", "lamp")
    add("lamp", "is the light on?", _yes_no(scene.lamp_on), "yes_no")
    add("lamp", "is the lamp off?", _yes_no(not scene.lamp_on), "yes_no")
    return {k: v for k, v in pool.items() if v}


KIND_WEIGHTS = {"caption": 1.0, "where": 2.0, "relation": 2.0, "superlative": 1.5, "bowl": 1.0, "stack": 1.0,
                "count": 1.0, "drawer": 1.0, "lamp": 1.0}


def sample_questions(scene: SceneState, rng: np.random.Generator, n: int) -> list[VQAItem]:
    """`n` distinct questions (fewer if the scene has fewer): a kind drawn by KIND_WEIGHTS, then an
    answer drawn uniformly among that kind's answers (so yes and no are balanced), then a question."""
    pool = question_pool(scene)
    kinds = sorted(pool)
    weights = np.array([KIND_WEIGHTS[k] for k in kinds])
    chosen: list[VQAItem] = []
    seen: set[str] = set()
    total = sum(len(v) for v in pool.values())
    for _ in range(20 * n):
        if len(chosen) >= min(n, total):
            break
        kind = kinds[int(rng.choice(len(kinds), p=weights / weights.sum()))]
        answers = sorted({item.answer for item in pool[kind]})
        answer = answers[int(rng.integers(len(answers)))]
        items = [item for item in pool[kind] if item.answer == answer]
        item = items[int(rng.integers(len(items)))]
        if item.question not in seen:
            seen.add(item.question)
            chosen.append(item)
    return chosen


# ---------------------------------------------------------------------------------------------
# Scenes


def _bowl_position(layout: Layout, offset_xy: tuple[float, float]) -> tuple[float, float, float]:
    local = np.array([offset_xy[0], offset_xy[1], BOWL_FLOOR + BLOCK_HALF + 0.0005, 1.0])
    x, y, z = (layout.bowl @ local)[:3]
    return float(x), float(y), float(z)


def sample_vqa_scene(rng: np.random.Generator, layout: Layout) -> SceneSpec:
    """A task-suite scene (a stack in 30% of them), with zero (60%), one (30%) or two (10%) of the
    blocks not in the stack moved into the bowl."""
    spec = sample_scene(rng, layout, stack=bool(rng.random() < 0.3))
    z = {c: p.position[2] for c, p in spec.blocks.items()}
    in_stack = set()
    for c, p in spec.blocks.items():
        if z[c] > 0.05:
            in_stack.add(c)
            base = min((b for b in spec.blocks if b != c),
                       key=lambda b: np.hypot(*(np.subtract(spec.blocks[b].position[:2], p.position[:2]))))
            in_stack.add(base)
    free = [c for c in BLOCK_COLORS if c not in in_stack]
    r = rng.random()
    count = min(len(free), 0 if r < 0.6 else 1 if r < 0.9 else 2)
    movers = [free[i] for i in rng.permutation(len(free))[:count]]
    blocks = dict(spec.blocks)
    offsets = [(float(rng.uniform(-0.02, 0.02)), float(rng.uniform(-0.02, 0.02)))] if count == 1 else [
        (-0.03 + float(rng.uniform(-0.004, 0.004)), float(rng.uniform(-0.01, 0.01))),
        (0.03 + float(rng.uniform(-0.004, 0.004)), float(rng.uniform(-0.01, 0.01))),
    ]
    for color, offset in zip(movers, offsets):
        blocks[color] = BlockPlacement(_bowl_position(layout, offset), float(rng.uniform(-0.3, 0.3)))
    return SceneSpec(blocks=blocks, drawer_opening=spec.drawer_opening, lamp_on=spec.lamp_on, arm_q=spec.arm_q)


class SceneRenderer:
    """A station (default scenario, cameras at `image_size`) that renders a `SceneSpec` from both
    cameras and reads back its `SceneState`."""

    def __init__(self, image_size: int) -> None:
        from trivla_drake.station.scenario import load_scenario
        from trivla_drake.station.station import make_station
        from trivla_drake.tasks.sim import StationHandles

        scenario = copy.deepcopy(load_scenario())
        for camera in scenario.cameras.values():
            camera.width = camera.height = int(image_size)
        self.station = make_station(scenario)
        self.context = self.station.CreateDefaultContext()
        self.handles = StationHandles(self.station)
        self.sensors = {}
        for key, name in (("static", "static_camera"), ("wrist", "wrist_camera")):
            if not self.station.HasSubsystemNamed(f"{name}_sensor"):
                raise ValueError(f"the default scenario has no camera {name!r}; System 2 needs both views")
            self.sensors[key] = self.station.GetSubsystemByName(f"{name}_sensor")

    def layout(self) -> Layout:
        """The fixtures' poses."""
        return self.handles.layout(self.context)

    def render(self, spec: SceneSpec) -> tuple[np.ndarray, np.ndarray, SceneState]:
        """(static uint8 (S, S, 3), wrist uint8 (S, S, 3), the scene's ground truth)."""
        self.handles.apply(self.context, spec)
        images = []
        for key in ("static", "wrist"):
            sensor = self.sensors[key]
            image = sensor.color_image_output_port().Eval(sensor.GetMyContextFromRoot(self.context))
            images.append(np.array(image.data[:, :, :3], dtype=np.uint8))
        return images[0], images[1], self.handles.read(self.context)

    def block_labels(self) -> np.ndarray:
        """uint8 (2, S, S) of the scene last rendered: per pixel of the static and wrist view, 1 + the
        index in BLOCK_COLORS of the block it shows, else 0 (from the cameras' label images, where
        the plant labels each geometry with its body's index)."""
        blocks = {int(body.index()): 1 + i for i, body in enumerate(self.handles.blocks[c] for c in BLOCK_COLORS)}
        views = []
        for key in ("static", "wrist"):
            sensor = self.sensors[key]
            raw = np.asarray(sensor.label_image_output_port().Eval(sensor.GetMyContextFromRoot(self.context)).data)
            raw = raw[:, :, 0].astype(np.int64)
            out = np.zeros(raw.shape, dtype=np.uint8)
            for label, value in blocks.items():
                out[raw == label] = value
            views.append(out)
        return np.stack(views)


# ---------------------------------------------------------------------------------------------
# The cached set


def vqa_settings(*, scenes: int, questions_per_scene: int, seed: int, image_size: int) -> dict[str, Any]:
    """What a VQA set depends on (its folder's key)."""
    return {"format": VQA_FORMAT_VERSION, "scenes": scenes, "questions_per_scene": questions_per_scene,
            "seed": seed, "image_size": image_size}


def vqa_key(settings: dict[str, Any]) -> str:
    """Short hash of the settings."""
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]


def generate_vqa_set(folder: str | os.PathLike, settings: dict[str, Any], *, progress: bool = True) -> Path:
    """Renders the scenes and writes the set to `folder` (atomically). Returns the folder."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    from tqdm import tqdm

    with atomic_folder(folder) as tmp:
        n, size = int(settings["scenes"]), int(settings["image_size"])
        renderer = SceneRenderer(size)
        layout = renderer.layout()
        static = np.lib.format.open_memmap(tmp / "static.npy", mode="w+", dtype=np.uint8, shape=(n, size, size, 3))
        wrist = np.lib.format.open_memmap(tmp / "wrist.npy", mode="w+", dtype=np.uint8, shape=(n, size, size, 3))
        labels = np.lib.format.open_memmap(tmp / "labels.npy", mode="w+", dtype=np.uint8, shape=(n, 2, size, size))
        rows: dict[str, list] = {k: [] for k in ("scene", "question", "answer", "kind", "answer_type", "split")}
        for i in tqdm(range(n), desc="rendering VQA scenes", unit="scene", disable=not progress):
            rng = np.random.default_rng([int(settings["seed"]), i])
            static[i], wrist[i], scene = renderer.render(sample_vqa_scene(rng, layout))
            labels[i] = renderer.block_labels()
            for item in sample_questions(scene, rng, int(settings["questions_per_scene"])):
                rows["scene"].append(i)
                rows["question"].append(item.question)
                rows["answer"].append(item.answer)
                rows["kind"].append(item.kind)
                rows["answer_type"].append(item.answer_type)
                rows["split"].append("eval" if i % EVAL_EVERY == EVAL_EVERY - 1 else "train")
        for array in (static, wrist, labels):
            array.flush()
        del static, wrist, labels
        pq.write_table(pa.table(rows), tmp / "qa.parquet")
        meta = {**settings, "questions": len(rows["scene"]), "eval_every": EVAL_EVERY}
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2))
    return Path(folder)


def read_vqa_meta(folder: str | os.PathLike) -> dict[str, Any] | None:
    """meta.json of a complete VQA set, or None if `folder` holds none."""
    path = Path(folder) / "meta.json"
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except ValueError:
        return None


def ensure_vqa_set(folder: str | os.PathLike, settings: dict[str, Any], *, progress: bool = True) -> Path:
    """The VQA set in `folder`, generated if absent. ValueError if `folder` holds a set made with
    other settings (it is never overwritten)."""
    return ensure_cached_folder(folder, settings, lambda: generate_vqa_set(folder, settings, progress=progress),
                                what="a VQA set")


class VQADataset:
    """Questions of one split of a VQA set with their scene's two views (memory-mapped)."""

    def __init__(self, folder: str | os.PathLike, split: str = "train") -> None:
        import pyarrow.parquet as pq

        self.folder = Path(folder)
        meta = read_vqa_meta(self.folder)
        if meta is None:
            raise ValueError(f"{self.folder} holds no VQA set (meta.json is missing)")
        if meta.get("format") != VQA_FORMAT_VERSION:
            raise ValueError(f"{self.folder} holds a VQA set of format {meta.get('format')!r}, this version reads "
                             f"format {VQA_FORMAT_VERSION} (with labels.npy): generate it again in another folder")
        self.meta = meta
        table = pq.read_table(self.folder / "qa.parquet").to_pydict()
        keep = [i for i, s in enumerate(table["split"]) if s == split]
        self.rows = {k: [v[i] for i in keep] for k, v in table.items()}
        self.static = np.load(self.folder / "static.npy", mmap_mode="r")
        self.wrist = np.load(self.folder / "wrist.npy", mmap_mode="r")
        self.labels = np.load(self.folder / "labels.npy", mmap_mode="r")

    @property
    def image_size(self) -> int:
        return int(self.static.shape[1])

    def __len__(self) -> int:
        return len(self.rows["scene"])

    def __getitem__(self, i: int) -> dict[str, Any]:
        scene = self.rows["scene"][i]
        return {
            "static_rgb": np.asarray(self.static[scene]),
            "wrist_rgb": np.asarray(self.wrist[scene]),
            "block_labels": np.asarray(self.labels[scene]),
            "instruction": self.rows["question"][i],
            "answer": self.rows["answer"][i],
            "answer_type": self.rows["answer_type"][i],
        }


def collate_vqa(items: list[dict[str, Any]]) -> dict[str, Any]:
    """Batch for `TriVLA.compute_vlm_loss`."""
    import torch

    return {
        "static_rgb": torch.from_numpy(np.stack([it["static_rgb"] for it in items])),
        "wrist_rgb": torch.from_numpy(np.stack([it["wrist_rgb"] for it in items])),
        "block_labels": torch.from_numpy(np.stack([it["block_labels"] for it in items])),
        "instruction": [it["instruction"] for it in items],
        "answer": [it["answer"] for it in items],
    }


# ---------------------------------------------------------------------------------------------
# Evaluation


def answer_log_likelihoods(model, static, wrist, questions: list[str], candidates: list[list[str]]) -> list:
    """log p(answer | images, question) of every candidate answer (see TriVLA.score_vlm_answers)."""
    return model.score_vlm_answers(static, wrist, questions, candidates)


def evaluate_vqa(model, dataset: VQADataset, *, batch_size: int = 8, max_questions: int = 400) -> dict[str, float]:
    """Accuracy on held-out questions with a closed answer set: the candidate answer with the highest
    likelihood is the model's answer. Returns overall and per-answer-type accuracy, and chance level.

    Also `vqa_accuracy_images_shuffled`: the same questions asked with another scene's images (those
    of the question half the list away). A model that reads the images falls toward chance; one that
    answers from the question alone scores the same as with its own images."""
    import torch

    index = [i for i in range(len(dataset)) if dataset.rows["answer_type"][i] in ANSWER_SETS][:max_questions]
    correct: dict[str, list[bool]] = {}
    shuffled: list[bool] = []
    chance: list[float] = []
    was_training = model.training
    model.eval()
    try:
        with torch.inference_mode():
            for start in range(0, len(index), batch_size):
                items = [dataset[i] for i in index[start : start + batch_size]]
                batch = collate_vqa(items)
                candidates = [list(ANSWER_SETS[it["answer_type"]]) for it in items]
                scores = answer_log_likelihoods(model, batch["static_rgb"], batch["wrist_rgb"],
                                                batch["instruction"], candidates)
                for item, cands, score in zip(items, candidates, scores):
                    guess = cands[int(score.argmax())]
                    correct.setdefault(item["answer_type"], []).append(guess == item["answer"])
                    chance.append(1.0 / len(cands))
                # The images of the question half the list away: another scene (when there is one).
                scene = dataset.rows["scene"]
                partners = [index[(j + len(index) // 2) % len(index)] for j in range(start, start + len(items))]
                keep = [k for k, p in enumerate(partners) if scene[p] != scene[index[start + k]]]
                others = {k: dataset[partners[k]] for k in keep}
                if keep:
                    swapped = collate_vqa([{**items[k], "static_rgb": others[k]["static_rgb"],
                                            "wrist_rgb": others[k]["wrist_rgb"]} for k in keep])
                    scores = answer_log_likelihoods(model, swapped["static_rgb"], swapped["wrist_rgb"],
                                                    swapped["instruction"], [candidates[k] for k in keep])
                    shuffled += [candidates[k][int(score.argmax())] == items[k]["answer"]
                                 for k, score in zip(keep, scores)]
    finally:
        model.train(was_training)
    every = [c for v in correct.values() for c in v]
    result = {"vqa_eval_questions": float(len(every)),
              "vqa_accuracy": float(np.mean(every)) if every else math.nan,
              "vqa_chance_accuracy": float(np.mean(chance)) if chance else math.nan,
              "vqa_accuracy_images_shuffled": float(np.mean(shuffled)) if shuffled else math.nan}
    for answer_type, values in sorted(correct.items()):
        result[f"vqa_accuracy_{answer_type}"] = float(np.mean(values))
    return result
