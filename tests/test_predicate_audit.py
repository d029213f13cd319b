"""results/predicate_audit/audit.py: reported successes read again after a hold, and more strictly."""

from __future__ import annotations

import json

import numpy as np

from trivla_drake.tasks.scene import Layout, scene_from_spec


def _scene_with(stacked_offset: float):
    """A scene whose red block stands on the blue one, its centre `stacked_offset` [m] off in x."""
    from trivla_drake.tasks.scene import BLOCK_SIZE, sample_scene

    layout = Layout.default()
    spec = sample_scene(np.random.default_rng(0), layout, stack=False)
    scene = scene_from_spec(spec, layout)
    blocks = dict(scene.blocks)
    top = blocks["blue"].copy()
    top[:3, 3] = blocks["blue"][:3, 3] + [stacked_offset, 0.0, BLOCK_SIZE]
    blocks["red"] = top
    scene.blocks = blocks
    scene.finger_width = 0.08
    return scene


def test_stricter_readings_refuse_what_the_review_found(results_script):
    audit = results_script("predicate_audit/audit.py")
    initial = _scene_with(0.0)
    # A top block 2.8 cm off its base passes stack's own predicate, not the stricter one; 1 cm off passes both.
    for offset, strict in ((0.028, False), (0.01, True)):
        scene = _scene_with(offset)
        assert audit.TASKS["stack_block"].success(("red", "blue"), initial, scene)
        assert audit.strict_success("stack_block", ("red", "blue"), initial, scene) is strict
    # A tower knocked over: the top lies on the table (a face up), the base shoved 8 cm. Unstack's own predicate
    # counts it; the stricter reading wants the base where it stood.
    knocked = _scene_with(0.0)
    blocks = dict(knocked.blocks)
    top, base = blocks["red"].copy(), blocks["blue"].copy()
    top[:3, 3] = base[:3, 3] + [0.0, 0.10, 0.0]
    base[0, 3] += 0.08
    blocks["red"], blocks["blue"] = top, base
    knocked.blocks = blocks
    assert audit.TASKS["unstack_block"].success(("red", "blue"), initial, knocked)
    assert not audit.strict_success("unstack_block", ("red", "blue"), initial, knocked)
    # A rotation that also shoved the block 10 cm: the predicate's yaw band passes, the stricter reading not.
    shoved = _scene_with(0.0)
    blocks = dict(shoved.blocks)
    moved = blocks["green"].copy()
    turn = np.deg2rad(30.0)
    moved[:3, :3] = np.array([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0], [0, 0, 1]]) @ moved[:3, :3]
    moved[0, 3] += 0.10
    blocks["green"] = moved
    shoved.blocks = blocks
    assert audit.TASKS["rotate_block_left"].success(("green",), initial, shoved)
    assert not audit.strict_success("rotate_block_left", ("green",), initial, shoved)


def test_the_oracle_s_successes_survive_every_reading(results_script, tmp_path):
    audit = results_script("predicate_audit/audit.py")
    out = tmp_path / "oracle.json"
    assert audit.main(["--policy", "oracle", "--seeds", "1000", "--episodes", "1", "--tasks",
                       "stack_block,unstack_block", "--out", str(out)]) == 0
    summary = json.loads(out.read_text())["summary"]
    for task in ("stack_block", "unstack_block"):
        assert summary[task] == {"episodes": 1, "successes": 1, "strict_at_success": 1, "success_after_hold": 1,
                                 "strict_after_hold": 1}


def test_the_hold_keeps_a_lifted_block_in_the_hand(results_script):
    """The hold keeps the last gripper command: a lift stays a lift (a first version opened the hand on a block
    45 mm wide and dropped every lifted block)."""
    audit = results_script("predicate_audit/audit.py")
    from trivla_drake.eval.episode import derive_seed
    from trivla_drake.tasks.oracle import OraclePolicy

    row = audit.audit_episode("lift_block", derive_seed(1000, "lift_block", 0), OraclePolicy())
    assert row["success"] and row["success_after_hold"] and row["after_hold"]["finger_width_m"] < 0.06
