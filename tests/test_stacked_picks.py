"""`--stacked-picks` (evaluate, collect): lift, place in bowl and stack episodes whose block to pick up starts on
top of another, the grasp 5-task chains ask for and the single-task scenes never have (results/chain_lifts/)."""

from __future__ import annotations

import numpy as np
import pytest

from trivla_drake.tasks.scene import Layout, scene_from_spec
from trivla_drake.tasks.suite import STACKED_PICK_TASKS, get_task, sample_task_instance


@pytest.mark.parametrize("name", STACKED_PICK_TASKS)
def test_the_block_to_pick_up_stands_on_another_and_never_does_by_default(name):
    layout = Layout.default()
    for seed in range(6):
        spec, instance = sample_task_instance(get_task(name), np.random.default_rng(seed), layout, stacked_pick=True)
        scene = scene_from_spec(spec, layout)
        assert scene.base_of(instance.params[0]) is not None
        assert get_task(name).candidates(scene)  # the task can start
        spec, instance = sample_task_instance(get_task(name), np.random.default_rng(seed), layout)
        assert scene_from_spec(spec, layout).base_of(instance.params[0]) is None


def test_other_tasks_are_refused_by_name():
    with pytest.raises(ValueError, match="not to unstack_block"):
        sample_task_instance(get_task("unstack_block"), np.random.default_rng(0), Layout.default(), stacked_pick=True)


def test_evaluate_s_flag_reaches_the_episodes_and_its_bad_uses_are_named():
    from trivla_drake.cli import build_parser
    from trivla_drake.eval.evaluate import EvalConfig, evaluate

    args = build_parser().parse_args(["evaluate", "--stacked-picks", "--tasks", "lift_block"])
    assert args.stacked_picks is True
    report = evaluate(EvalConfig(policy="oracle", tasks=["lift_block", "turn_on_light"], episodes=1, stacked_picks=True),
                      progress=False)
    assert report["tasks"]["lift_block"]["successes"] == 1  # the oracle lifts a block off another
    assert report["config"]["stacked_picks"] is True
    with pytest.raises(ValueError, match="--stacked-picks applies to"):
        EvalConfig(tasks=["open_drawer"], episodes=1, stacked_picks=True).validate()
    with pytest.raises(ValueError, match="--stacked-picks and --prelude"):
        EvalConfig(tasks=["lift_block"], episodes=1, stacked_picks=True, prelude=1).validate()


@pytest.mark.parametrize("value", [-0.1, 1.5, True, "half"])
def test_bad_stacked_pick_fractions_name_the_flag(value):
    from trivla_drake.eval.collect import CollectConfig

    with pytest.raises(ValueError, match="--stacked-picks"):
        CollectConfig(out="unused", episodes_per_task=1, stacked_picks=value).validate()
    with pytest.raises(ValueError, match="--stacked-picks and --prelude-tasks"):
        CollectConfig(out="unused", episodes_per_task=1, stacked_picks=0.5, prelude_tasks=1).validate()


def test_collected_episodes_say_when_their_block_started_on_another(tmp_path):
    from trivla_drake.cli import build_parser
    from trivla_drake.data.lerobot import STACKED_PICK_KEY, LeRobotReader
    from trivla_drake.eval.collect import CollectConfig, collect

    args = build_parser().parse_args(["collect", "--out", "x", "--episodes-per-task", "1", "--stacked-picks", "0.3"])
    assert args.stacked_picks == 0.3
    out = tmp_path / "stacked"
    collect(CollectConfig(out=str(out), episodes_per_task=1, tasks=["lift_block"], image_size=32, stacked_picks=1.0),
            progress=False)
    reader = LeRobotReader(out)
    assert reader.episodes[0][STACKED_PICK_KEY] is True
    # And it did start stacked: the hand first closes (the action's gripper command turns to close) a block's height
    # above the table (block centre 0.0225 m, on another 0.0675 m), not at table height.
    frames = reader.episode_frames(0)
    first_close = int(np.flatnonzero(frames["action"][:, 6] < 0)[0])
    assert frames["observation.tcp_pose"][first_close, 2] > 0.05
