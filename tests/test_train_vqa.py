"""System 2's simulator-generated visual questions: answers follow the ground truth, ambiguous
questions are not asked, answers are balanced, and the rendered set is made once and reused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from trivla_drake.tasks.scene import BlockPlacement, Layout, SceneSpec, scene_from_spec
from trivla_drake.train import vqa


def _scene(blocks: dict[str, tuple[float, float, float]], *, drawer=0.0, lamp=False):
    spec = SceneSpec(blocks={c: BlockPlacement(p, 0.0) for c, p in blocks.items()}, drawer_opening=drawer, lamp_on=lamp)
    return scene_from_spec(spec, Layout.default())


@pytest.fixture
def scene():
    # red in the bowl (bowl centre 0.45, 0.30), green stacked on blue near the robot on its right.
    return _scene({"red": (0.45, 0.30, 0.0305), "green": (0.38, -0.10, 0.068), "blue": (0.38, -0.10, 0.0225)},
                  drawer=0.12, lamp=False)


def _answers(scene) -> dict[str, str]:
    return {item.question: item.answer for items in vqa.question_pool(scene).values() for item in items}


def test_answers_follow_the_ground_truth(scene):
    qa = _answers(scene)
    assert qa["is the red block in the bowl?"] == "yes"
    assert qa["is the green block in the bowl?"] == "no"
    assert qa["how many blocks are in the bowl?"] == "one"
    assert qa["what colour is the block in the bowl?"] == "red"
    assert qa["how many blocks are on the table?"] == "one"
    assert qa["which block is on top of another block?"] == "green"
    assert qa["what colour is the block under the green block?"] == "blue"
    assert qa["is the green block stacked on the blue block?"] == "yes"
    assert qa["is the blue block stacked on the green block?"] == "no"
    assert qa["where is the red block?"] == "in the bowl"
    assert qa["where is the green block?"] == "on top of the blue block"
    assert qa["where is the blue block?"] == "on the table, near the robot, on the right"
    assert qa["is the red block to the left of the blue block?"] == "yes"
    assert qa["is the blue block to the left of the red block?"] == "no"
    assert qa["which block is furthest to the left?"] == "red"
    assert qa["is the drawer open or closed?"] == "open"
    assert qa["is the lamp on or off?"] == "off"
    assert qa["is the light on?"] == "no"
    assert qa["describe the scene."] == (
        "The red block is in the bowl. The green block is on top of the blue block. The blue block is on the "
        "table, near the robot, on the right. The drawer is open. The lamp is off."
    )


def test_ambiguous_questions_are_not_asked(scene):
    qa = _answers(scene)
    # green and blue share x, y: no left/right relation and no unique rightmost block
    assert "is the green block to the left of the blue block?" not in qa
    assert "which block is furthest to the right?" not in qa
    # a block 5 mm from the centre/left band edge gets no side
    edge = _scene({"red": (0.36, vqa.SIDE_EDGES[1] + 0.005, 0.0225), "green": (0.55, -0.12, 0.0225),
                   "blue": (0.55, 0.15, 0.0225)})
    assert _answers(edge)["where is the red block?"] == "on the table, near the robot"
    assert _answers(edge)["where is the blue block?"] == "on the table, far from the robot, on the left"


def test_sampled_questions_are_distinct_and_answers_balanced():
    rng = np.random.default_rng(0)
    layout = Layout.default()
    yes = no = 0
    kinds: set[str] = set()
    in_bowl = 0
    for _ in range(60):
        spec = vqa.sample_vqa_scene(rng, layout)
        scene = scene_from_spec(spec, layout)
        in_bowl += any(scene.in_bowl(c) for c in scene.blocks)
        items = vqa.sample_questions(scene, rng, 8)
        assert len(items) == 8 and len({i.question for i in items}) == 8
        for item in items:
            kinds.add(item.kind)
            if item.answer_type in vqa.ANSWER_SETS:
                assert item.answer in vqa.ANSWER_SETS[item.answer_type]
            yes += item.answer == "yes"
            no += item.answer == "no"
    assert kinds == set(vqa.KIND_WEIGHTS)
    assert 0.35 < yes / (yes + no) < 0.65
    assert 0.25 < in_bowl / 60 < 0.6  # 40% of the scenes have blocks in the bowl


def test_rendered_scenes_show_the_state_and_the_set_is_made_once(tmp_path, monkeypatch):
    renderer = vqa.SceneRenderer(64)
    layout = renderer.layout()
    spec = vqa.sample_vqa_scene(np.random.default_rng(3), layout)
    closed_off = SceneSpec(blocks=spec.blocks, drawer_opening=0.0, lamp_on=False, arm_q=spec.arm_q)
    static, wrist, state = renderer.render(closed_off)
    assert static.shape == wrist.shape == (64, 64, 3) and static.dtype == np.uint8
    # the label maps mark each block's pixels, which have that block's colour
    labels = renderer.block_labels()
    assert labels.shape == (2, 64, 64) and labels.dtype == np.uint8 and labels.max() <= len(vqa.BLOCK_COLORS)
    assert set(np.unique(labels[0])) == {0, 1, 2, 3}
    for k, color in enumerate(vqa.BLOCK_COLORS):
        mean_rgb = static[labels[0] == k + 1].astype(float).mean(axis=0)
        assert int(np.argmax(mean_rgb)) == ("red", "green", "blue").index(color), (color, mean_rgb)
    assert not state.lamp_on and state.drawer_opening == pytest.approx(0.0)
    for changed in (SceneSpec(blocks=spec.blocks, drawer_opening=0.13, lamp_on=False, arm_q=spec.arm_q),
                    SceneSpec(blocks=spec.blocks, drawer_opening=0.0, lamp_on=True, arm_q=spec.arm_q)):
        other, _, other_state = renderer.render(changed)
        assert other_state.lamp_on == changed.lamp_on
        assert np.abs(other.astype(int) - static.astype(int)).sum() > 0  # the change is visible

    settings = vqa.vqa_settings(scenes=10, questions_per_scene=5, seed=0, image_size=64)
    folder = vqa.ensure_vqa_set(tmp_path / "vqa", settings, progress=False)
    train_set, eval_set = vqa.VQADataset(folder, "train"), vqa.VQADataset(folder, "eval")
    assert len(train_set) == 45 and len(eval_set) == 5  # scene 9 is held out
    item = train_set[0]
    assert item["static_rgb"].shape == (64, 64, 3) and item["answer"]
    assert item["block_labels"].shape == (2, 64, 64) and item["block_labels"].max() > 0
    assert vqa.collate_vqa([item, item])["block_labels"].shape == (2, 2, 64, 64)
    assert len({train_set.static[i].tobytes() for i in range(10)}) == 10  # every scene differs

    def fail(*args, **kwargs):
        raise AssertionError("the VQA set was generated again")

    monkeypatch.setattr(vqa, "generate_vqa_set", fail)
    assert vqa.ensure_vqa_set(folder, settings) == folder
    with pytest.raises(ValueError, match="other settings"):
        vqa.ensure_vqa_set(folder, {**settings, "scenes": 11})
    # a set of the format before the label maps is named, not read half
    meta = json.loads((folder / "meta.json").read_text())
    (folder / "meta.json").write_text(json.dumps({**meta, "format": 1}))
    with pytest.raises(ValueError, match="format 1.*labels.npy"):
        vqa.VQADataset(folder, "train")


def test_answer_scores_are_the_lm_loss_of_each_candidate():
    import torch

    from trivla_drake.nn import TriVLA, make_config

    torch.set_num_threads(1)
    model = TriVLA(make_config("tiny", use_system3=False)).eval()
    rng = np.random.default_rng(0)
    static = torch.from_numpy(rng.integers(0, 255, (2, 224, 224, 3), dtype=np.uint8))
    wrist = torch.from_numpy(rng.integers(0, 255, (2, 224, 224, 3), dtype=np.uint8))
    questions = ["is the lamp on or off?", "which block is closest to the robot?"]
    candidates = [["on", "off"], ["red", "green", "blue", "none"]]
    with torch.inference_mode():
        scores = vqa.answer_log_likelihoods(model, static, wrist, questions, candidates)
        for b, cands in enumerate(candidates):
            assert scores[b].shape == (len(cands),)
            for k, answer in enumerate(cands):
                loss, _ = model.compute_vlm_loss({"static_rgb": static[b : b + 1], "wrist_rgb": wrist[b : b + 1],
                                                  "instruction": [questions[b]], "answer": [answer]})
                tokens = len(answer.encode()) + 1  # the answer's bytes and the end-of-turn token
                assert float(scores[b][k]) == pytest.approx(-float(loss) * tokens, rel=1e-4, abs=1e-4)


class _LookupModel:
    """A stand-in for TriVLA's answer scoring: answers from a table keyed by (image, question) when
    `sees`, else from the question alone (the same answer whatever the scene)."""

    def __init__(self, dataset, sees: bool):
        self.sees, self.training = sees, False
        self.truth = {(dataset.static[dataset.rows["scene"][i]].tobytes(), dataset.rows["question"][i]):
                      dataset.rows["answer"][i] for i in range(len(dataset))}

    def eval(self):
        return self

    def train(self, mode=True):
        return self

    def score_vlm_answers(self, static, wrist, questions, candidates):
        import torch

        out = []
        for image, question, cands in zip(static, questions, candidates):
            answer = self.truth.get((image.numpy().tobytes(), question)) if self.sees else cands[-1]
            out.append(torch.tensor([1.0 if c == answer else 0.0 for c in cands]))
        return out


def test_vqa_accuracy_with_shuffled_images_tells_a_grounded_model_from_a_blind_one(tmp_path):
    settings = vqa.vqa_settings(scenes=20, questions_per_scene=6, seed=1, image_size=64)
    dataset = vqa.VQADataset(vqa.ensure_vqa_set(tmp_path / "vqa", settings, progress=False), "train")
    seeing = vqa.evaluate_vqa(_LookupModel(dataset, sees=True), dataset, batch_size=4)
    assert seeing["vqa_accuracy"] == 1.0
    assert seeing["vqa_accuracy_images_shuffled"] < 0.8  # another scene's images give other answers
    blind = vqa.evaluate_vqa(_LookupModel(dataset, sees=False), dataset, batch_size=4)
    assert blind["vqa_accuracy_images_shuffled"] == pytest.approx(blind["vqa_accuracy"])
