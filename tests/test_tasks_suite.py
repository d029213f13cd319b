"""The task suite without simulation: names, instructions, sampling, predicates, the action space."""

from __future__ import annotations

import math

import numpy as np
import pytest

from trivla_drake.systems.action_executor import (
    ACTION_HIGH,
    ACTION_LOW,
    CLOSED_WIDTH,
    OPEN_WIDTH,
    apply_action,
    delta_action,
    exp_so3,
    log_so3,
)
from trivla_drake.tasks import TASK_NAMES, TASKS, Layout, UnknownTaskError, get_task, parse_task_list
from trivla_drake.tasks.chains import chain_options, next_chain_task
from trivla_drake.tasks.scene import BLOCK_COLORS, SceneSpec, sample_scene, scene_from_spec, tcp_pose
from trivla_drake.tasks.suite import sample_task_instance

LAYOUT = Layout.default()


def test_suite_has_at_least_ten_tasks_with_disjoint_paraphrases():
    assert len(TASKS) >= 10
    for task in TASKS.values():
        assert len(task.templates) >= 3 and len(task.paraphrases) >= 3, task.name
        train = set(task.all_instructions())
        held_out = set(task.all_instructions(paraphrase=True))
        assert not train & held_out, task.name
    # No paraphrase of any task is a training instruction of any other task either.
    every_train = {t for task in TASKS.values() for t in task.all_instructions()}
    every_held_out = {t for task in TASKS.values() for t in task.all_instructions(paraphrase=True)}
    assert not every_train & every_held_out


def test_unknown_task_name_lists_the_valid_ones():
    with pytest.raises(UnknownTaskError) as error:
        get_task("juggle_blocks")
    for name in TASK_NAMES:
        assert name in str(error.value)
    with pytest.raises(ValueError, match="open_drawer"):
        parse_task_list("lift_block,fly")
    assert parse_task_list("all") == list(TASK_NAMES)
    assert parse_task_list("lift_block, open_drawer") == ["lift_block", "open_drawer"]


@pytest.mark.parametrize("name", TASK_NAMES)
def test_sampled_instances_are_seeded_and_start_unsolved(name):
    task = get_task(name)
    instructions, params = set(), set()
    for seed in range(12):
        spec, instance = sample_task_instance(task, np.random.default_rng(seed), LAYOUT)
        again, instance_again = sample_task_instance(task, np.random.default_rng(seed), LAYOUT)
        assert spec == again and instance == instance_again  # the same seed, the same episode
        scene = scene_from_spec(spec, LAYOUT)
        assert instance.params in task.candidates(scene)
        assert not task.success(instance.params, scene, scene), (name, seed)
        assert instance.instruction in task.all_instructions()
        instructions.add(instance.instruction)
        params.add(instance.params)
    assert len(instructions) > 1  # templates are drawn at random
    if TASKS[name].templates[0].count("{color}"):
        assert len(params) > 1  # so is the target block
    _, paraphrased = sample_task_instance(task, np.random.default_rng(0), LAYOUT, paraphrase=True)
    assert paraphrased.instruction in task.all_instructions(paraphrase=True)


def test_start_postures_are_randomised():
    specs = [sample_scene(np.random.default_rng(s), LAYOUT) for s in range(5)]
    postures = np.array([s.arm_q for s in specs])
    assert np.all(np.ptp(postures, axis=0) > 0.01)
    for spec in specs:  # blocks apart and off the fixtures
        scene = scene_from_spec(spec, LAYOUT)
        for color in BLOCK_COLORS:
            p = scene.block_position(color)
            assert scene.obstacle_clearance(p) > 0.04
            assert scene.block_clearance(p, exclude=(color,)) >= 0.09


def _scene(blocks: dict, **kwargs):
    spec = SceneSpec(blocks=blocks, **kwargs)
    return scene_from_spec(spec, LAYOUT)


def _placed(positions: dict):
    from trivla_drake.tasks.scene import BlockPlacement

    return {c: BlockPlacement(tuple(p), yaw) for c, (p, yaw) in positions.items()}


def test_block_predicates_follow_the_geometry():
    far = {"green": ((0.4, -0.1, 0.0225), 0.0), "blue": ((0.55, -0.1, 0.0225), 0.0)}
    start = _scene(_placed({"red": ((0.45, 0.05, 0.0225), 0.1), **far}))
    lift, push_left, rotate_left = get_task("lift_block"), get_task("push_block_left"), get_task("rotate_block_left")
    assert not lift.success(("red",), start, start)
    lifted = _scene(_placed({"red": ((0.45, 0.05, 0.15), 0.1), **far}))
    assert lift.success(("red",), start, lifted)
    pushed = _scene(_placed({"red": ((0.46, 0.12, 0.0225), 0.1), **far}))
    assert push_left.success(("red",), start, pushed)
    assert not get_task("push_block_right").success(("red",), start, pushed)
    turned = _scene(_placed({"red": ((0.45, 0.05, 0.0225), 0.1 + math.radians(30)), **far}))
    assert rotate_left.success(("red",), start, turned)
    assert not get_task("rotate_block_right").success(("red",), start, turned)
    # A quarter turn looks like no turn at all for a cube: not a success.
    quarter = _scene(_placed({"red": ((0.45, 0.05, 0.0225), 0.1 + math.pi / 2), **far}))
    assert not rotate_left.success(("red",), start, quarter)
    in_bowl = _scene(_placed({"red": ((0.45, 0.3, 0.031), 0.0), **far}))
    assert get_task("place_in_bowl").success(("red",), start, in_bowl)
    stacked = _scene(_placed({"red": ((0.401, -0.1, 0.068), 0.0), **far}))
    assert get_task("stack_block").success(("red", "green"), start, stacked)
    assert get_task("unstack_block").candidates(stacked) == [("red", "green")]
    assert not get_task("unstack_block").success(("red", "green"), stacked, stacked)
    # A block held in the closed hand over the bowl is not "placed".
    held = _scene(_placed({"red": ((0.45, 0.3, 0.045), 0.0), **far}))
    held.tcp, held.finger_width = tcp_pose([0.45, 0.3, 0.045], 0.0), 0.045
    assert held.is_held("red") and not get_task("place_in_bowl").success(("red",), start, held)


def test_placing_in_a_full_bowl_has_no_plan_and_says_why():
    # The bowl sits at (0.45, 0.3): green and blue fill both of its places.
    full = _scene(_placed({"red": ((0.4, -0.1, 0.0225), 0.0), "green": ((0.417, 0.3, 0.031), 0.0),
                           "blue": ((0.483, 0.3, 0.031), 0.0)}))
    task = get_task("place_in_bowl")
    assert ("red",) not in task.candidates(full)
    with pytest.raises(ValueError, match="no free place for the red block"):
        task.plan(("red",), full)


def test_fixture_predicates():
    blocks = _placed({c: ((0.4 + 0.1 * i, 0.0, 0.0225), 0.0) for i, c in enumerate(BLOCK_COLORS)})
    closed, opened = _scene(blocks), _scene(blocks, drawer_opening=0.13)
    assert get_task("open_drawer").success((), closed, opened)
    assert not get_task("open_drawer").success((), closed, closed)
    assert get_task("close_drawer").success((), opened, closed)
    assert get_task("open_drawer").candidates(closed) == [()] and get_task("open_drawer").candidates(opened) == []
    dark, lit = _scene(blocks), _scene(blocks, lamp_on=True)
    assert get_task("turn_on_light").success((), dark, lit) and not get_task("turn_on_light").success((), dark, dark)
    assert get_task("turn_off_light").success((), lit, dark)


def test_chain_generator_picks_only_possible_unused_tasks():
    rng = np.random.default_rng(0)
    spec = sample_scene(rng, LAYOUT, drawer_open=False, lamp_on=False)
    scene = scene_from_spec(spec, LAYOUT)
    options = chain_options(scene, set())
    assert "close_drawer" not in options and "turn_off_light" not in options and "unstack_block" not in options
    assert "open_drawer" in options and "turn_on_light" in options
    instance = next_chain_task(scene, rng, {"open_drawer"})
    assert instance.task != "open_drawer"
    # With a block in the hand only tasks that put it somewhere can follow.
    held = scene_from_spec(spec, LAYOUT)
    held.blocks = dict(held.blocks)
    held.blocks["red"] = held.blocks["red"].copy()
    held.blocks["red"][2, 3] = 0.15
    held.tcp, held.finger_width = tcp_pose(held.blocks["red"][:3, 3], 0.0), 0.045
    assert set(chain_options(held, set())) <= {"place_in_bowl", "stack_block"}


def test_action_space_round_trip_and_bounds():
    X = tcp_pose([0.45, 0.0, 0.2], 0.3)
    goal = tcp_pose([0.452, -0.003, 0.195], 0.32)
    action = delta_action(X, goal, 1.0)
    X_next, width = apply_action(X, action)
    np.testing.assert_allclose(X_next, goal, atol=1e-12)
    assert width == OPEN_WIDTH
    # Large requests are clipped per component; the gripper command is a sign.
    huge = np.array([1.0, -1.0, 0.0, 0.0, 0.0, 2.0, -0.2])
    X_next, width = apply_action(X, huge)
    np.testing.assert_allclose(X_next[:3, 3] - X[:3, 3], [ACTION_HIGH[0], ACTION_LOW[1], 0.0])
    np.testing.assert_allclose(log_so3(X_next[:3, :3] @ X[:3, :3].T), [0.0, 0.0, ACTION_HIGH[5]], atol=1e-12)
    assert width == CLOSED_WIDTH
    # The target cannot leave the workspace box.
    low = tcp_pose([0.45, 0.0, 0.006], 0.0)
    X_next, _ = apply_action(low, np.array([0, 0, -0.01, 0, 0, 0, 1.0]))
    assert X_next[2, 3] >= 0.005
    rotvec = np.array([0.3, -0.2, 0.1])
    np.testing.assert_allclose(log_so3(exp_so3(rotvec)), rotvec, atol=1e-12)
    with pytest.raises(ValueError, match="shape"):
        apply_action(X, np.zeros(6))
    with pytest.raises(ValueError, match="NaN"):
        apply_action(X, np.array([np.nan, 0, 0, 0, 0, 0, 1]))


def test_hand_body_keeps_clear_of_the_open_drawer():
    from trivla_drake.tasks import motions

    far = {"green": ((0.38, 0.1, 0.0225), 0.0), "blue": ((0.38, -0.05, 0.0225), 0.0)}
    near_drawer = _placed({"red": ((0.52, -0.115, 0.0225), 0.1), **far})
    opened, closed = _scene(near_drawer, drawer_opening=0.13), _scene(near_drawer)
    # Fingers closing along y would put the hand's body over the open drawer: turn the hand.
    yaw = motions.grasp_yaw(opened, "red")
    assert abs(abs(yaw - 0.1) - math.pi / 2) < 1e-9
    assert opened.hand_clearance(opened.block_position("red"), 0.1) < 0.0
    assert opened.hand_clearance(opened.block_position("red"), yaw) > 0.01
    assert closed.hand_clearance(closed.block_position("red"), 0.1) > 0.0
    assert ("red",) in get_task("lift_block").candidates(opened)
    # A push to the left starts beside the cabinet, the hand's body across the push: too close to
    # the handle here, fine a bit further from the cabinet unless the drawer is open.
    assert ("red",) not in get_task("push_block_left").candidates(closed)
    further = _placed({"red": ((0.45, -0.115, 0.0225), 0.1), **far})
    assert ("red",) in get_task("push_block_left").candidates(_scene(further))
    assert ("red",) not in get_task("push_block_left").candidates(_scene(further, drawer_opening=0.13))


def test_a_task_named_twice_is_refused_in_evaluate(capsys):
    from trivla_drake.eval.cli_commands import main
    from trivla_drake.eval.evaluate import EvalConfig

    with pytest.raises(ValueError, match=r"--tasks names \['lift_block'\] more than once"):
        EvalConfig(policy="oracle", tasks=["lift_block", "lift_block"]).validate()
    assert main(["evaluate", "--policy", "oracle", "--tasks", "lift_block,open_drawer,lift_block"]) == 2
    assert "--tasks names ['lift_block'] more than once" in capsys.readouterr().err


def test_collect_refuses_what_evaluate_refuses():
    """A task named twice would record every attempt twice; a seed past 32 bits wraps onto another's scenes."""
    from trivla_drake.eval.collect import CollectConfig
    from trivla_drake.eval.evaluate import EvalConfig

    for kwargs, message in (({"tasks": ["lift_block", "lift_block"]}, r"--tasks names \['lift_block'\] more than once"),
                            ({"tasks": ["lift_block"], "seed": 2**32}, "--seed must be an integer from 0 to 4294967295"),
                            ({"tasks": ["lift_block"], "seed": -1}, "--seed must be an integer")):
        with pytest.raises(ValueError, match=message):
            CollectConfig(out="unused", episodes_per_task=1, **kwargs).validate()
        with pytest.raises(ValueError, match=message):
            EvalConfig(episodes=1, **kwargs).validate()


def test_unstack_plan_without_a_free_spot_says_so():
    from trivla_drake.tasks.scene import Layout, sample_scene, scene_from_spec
    from trivla_drake.tasks.suite import _free_spot

    layout, task = Layout.default(), get_task("unstack_block")
    rng = np.random.default_rng(0)
    for _ in range(3000):
        scene = scene_from_spec(sample_scene(rng, layout, stack=True), layout)
        top = next(c for c in scene.blocks if scene.base_of(c))
        if _free_spot(scene, top, scene.block_position(scene.base_of(top))) is None:
            with pytest.raises(ValueError, match=f"unstack_block: no free place on the table to set the {top} block"):
                task.plan((top, scene.base_of(top)), scene)
            return
    pytest.skip("no stacked scene without a free spot in 3000 draws")
