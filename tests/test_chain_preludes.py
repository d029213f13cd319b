"""Chain preludes (`collect --set prelude_tasks=N`, `evaluate --set prelude=N`; the registered episode start
"chain_prelude", eval/episode_starts.py): before the recorded task the oracle completes one or more
other tasks of a chain, unrecorded, so the demonstration starts where a chain's earlier tasks leave the
scene and the hand, as the second to fifth tasks of a 5-task chain do. Never a lift (it leaves the block
in the hand); a prelude that fails, or leaves the task no way to start, fails the attempt with the
reason. Bad settings are refused naming the field."""

from __future__ import annotations

import numpy as np
import pytest

from trivla_drake.data.lerobot_format import PRELUDE_KEY
from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.tasks.chains import prelude_task
from trivla_drake.tasks.scene import Layout, sample_scene, scene_from_spec


def _scene(seed: int):
    layout = Layout.default()
    return scene_from_spec(sample_scene(np.random.default_rng(seed), layout), layout)


def test_a_prelude_task_is_possible_now_never_a_lift_and_never_excluded():
    seen = set()
    for seed in range(40):
        rng = np.random.default_rng(seed)
        instance = prelude_task(_scene(seed), rng, exclude={"push_block_left", "open_drawer"})
        assert instance is not None
        assert instance.task not in {"lift_block", "push_block_left", "open_drawer"}
        seen.add(instance.task)
    assert len(seen) >= 5  # drawn among the possible tasks, not always the same


def test_no_prelude_task_when_every_possible_task_is_excluded():
    from trivla_drake.tasks.suite import TASK_NAMES

    assert prelude_task(_scene(0), np.random.default_rng(0), exclude=set(TASK_NAMES)) is None


def test_the_episode_starts_where_the_prelude_left_the_hand():
    from trivla_drake.eval.episode import run_episode
    from trivla_drake.eval.episode_starts import make_episode_start
    from trivla_drake.tasks.oracle import OraclePolicy

    plain = run_episode("turn_on_light", 123, OraclePolicy(), keep_trajectory=True)
    chained = run_episode("turn_on_light", 123, OraclePolicy(), keep_trajectory=True,
                          start=make_episode_start("chain_prelude", tasks=1))
    assert plain.success and chained.success, chained.reason
    assert plain.prelude == () and "prelude" not in plain.to_dict()
    assert len(chained.prelude) == 1 and chained.prelude[0] not in {"turn_on_light", "lift_block"}
    assert chained.to_dict()["prelude"] == list(chained.prelude)
    # Same scene seed, but the recorded hand starts elsewhere: where the prelude's task ended.
    start_plain, start_chained = plain.trajectory.tcp_poses[0][:3], chained.trajectory.tcp_poses[0][:3]
    assert np.linalg.norm(start_plain - start_chained) > 0.05
    assert len(chained.trajectory) == chained.steps  # only the episode's own task is recorded


def test_a_prelude_with_nothing_to_run_fails_the_episode_with_the_reason(monkeypatch):
    from trivla_drake.eval import episode_starts
    from trivla_drake.eval.episode import run_episode
    from trivla_drake.tasks.oracle import OraclePolicy

    monkeypatch.setattr(episode_starts, "prelude_task", lambda scene, rng, exclude: None)  # no task possible
    result = run_episode("open_drawer", 3, OraclePolicy(), start=episode_starts.make_episode_start("chain_prelude",
                                                                                                   tasks=2))
    assert not result.success and result.steps == 0 and result.start_failed
    assert result.reason.startswith("prelude: no task can run")
    assert not run_episode("open_drawer", 3, OraclePolicy(), max_steps=1).start_failed  # a plain failure is none


def test_episode_starts_are_made_by_registered_name():
    from trivla_drake.eval.episode_starts import EPISODE_STARTS, ChainPrelude, make_episode_start

    assert "chain_prelude" in EPISODE_STARTS.names()
    start = make_episode_start("chain_prelude", tasks=3)
    assert isinstance(start, ChainPrelude) and start.tasks == 3 and start.policy.privileged
    with pytest.raises(ValueError, match=r"unknown episode start 'home'; registered: .*chain_prelude"):
        make_episode_start("home")
    with pytest.raises(ValueError, match="settings of the episode start 'chain_prelude'.*count"):
        make_episode_start("chain_prelude", count=2)


@pytest.mark.parametrize("tasks", [0, -1, 5, 1.5, True])
def test_bad_chain_prelude_settings_name_the_field(tasks):
    from trivla_drake.eval.episode_starts import make_episode_start

    with pytest.raises(ValueError, match="chain_prelude: tasks must be an integer from 1 to 4"):
        make_episode_start("chain_prelude", tasks=tasks)


def test_run_episode_refuses_a_start_that_is_no_episode_start():
    from trivla_drake.eval.episode import run_episode
    from trivla_drake.tasks.oracle import OraclePolicy

    with pytest.raises(TypeError, match="start must be an episode start"):
        run_episode("open_drawer", 0, OraclePolicy(), start=2)


@pytest.mark.parametrize("value", [-1, 5, True, 1.0])
def test_bad_prelude_tasks_settings_name_the_field(value):
    from trivla_drake.eval.collect import CollectConfig

    with pytest.raises(ValueError, match="prelude_tasks must be"):
        CollectConfig(out="unused", episodes_per_task=1, prelude_tasks=value).validate()


def test_collected_episodes_list_their_prelude(tmp_path):
    from trivla_drake.eval.collect import CollectConfig, collect

    out = tmp_path / "chained"
    summary = collect(
        CollectConfig(out=str(out), episodes_per_task=1, tasks=["turn_off_light"], image_size=32, prelude_tasks=2),
        progress=False,
    )
    assert summary["per_task"] == {"turn_off_light": 1}
    reader = LeRobotReader(out)
    episode = reader.episodes[0]
    assert 1 <= len(episode[PRELUDE_KEY]) <= 2
    # One camera frame per recorded step: the prelude's last step rendered none, the first row has its own.
    rows = len(reader.episode_frames(0)["action"])
    for camera in ("observation.images.static", "observation.images.wrist"):
        assert len(reader.episode_video(0, camera)) == rows
    assert "turn_off_light" not in episode[PRELUDE_KEY] and "lift_block" not in episode[PRELUDE_KEY]


def test_evaluate_with_a_prelude_starts_each_episode_after_the_oracle_s_chain_tasks():
    from trivla_drake.eval.evaluate import EvalConfig, evaluate

    report = evaluate(EvalConfig(policy="oracle", tasks=["close_drawer"], episodes=1, prelude=1), progress=False)
    assert report["tasks"]["close_drawer"]["successes"] == 1
    assert report["config"]["prelude"] == 1
    ((before, row),) = report["after_prelude_task"].items()
    assert before != "close_drawer" and row == {"tried": 1, "succeeded": 1}


def test_success_is_pooled_by_the_task_just_before_and_failures_name_their_prelude():
    from trivla_drake.eval.evaluate import EvalConfig, format_markdown, success_after_prelude_task, summarize

    def episode(task, prelude, success):
        return {"task": task, "seed": 7, "instruction": "do it", "success": success,
                "reason": "" if success else "timeout", **({"prelude": prelude} if prelude else {})}

    episodes = [episode("lift_block", ["open_drawer"], False), episode("lift_block", ["turn_on_light", "open_drawer"], True),
                episode("stack_block", ["turn_on_light"], True), episode("stack_block", [], False)]
    assert success_after_prelude_task(episodes) == {"open_drawer": {"tried": 2, "succeeded": 1},
                                                   "turn_on_light": {"tried": 1, "succeeded": 1}}
    report = summarize(EvalConfig(tasks=["lift_block", "stack_block"], episodes=2, prelude=2), episodes, [])
    assert report["tasks"]["lift_block"]["failures"][0]["prelude"] == ["open_drawer"]
    assert "prelude" not in report["tasks"]["stack_block"]["failures"][0]  # its prelude never completed
    text = format_markdown(report)
    assert "| after the prelude's last task | open_drawer | turn_on_light |" in text
    assert "| succeeded / tried | 1 / 2 | 1 / 1 |" in text
    assert "- lift_block (seed 7 after open_drawer): timeout" in text
    assert "after_prelude_task" not in summarize(EvalConfig(tasks=["lift_block"], episodes=1), episodes[:1], [])


def test_evaluate_redraws_a_failed_prelude_then_reports_its_reason(monkeypatch):
    import trivla_drake.eval.episode_starts as episode_starts
    from trivla_drake.eval.evaluate import PRELUDE_REDRAWS, EvalConfig, evaluate

    calls = []

    def nothing_possible(scene, rng, exclude):
        calls.append(1)
        return None

    monkeypatch.setattr(episode_starts, "prelude_task", nothing_possible)
    report = evaluate(EvalConfig(policy="oracle", tasks=["open_drawer"], episodes=1, prelude=2), progress=False)
    assert len(calls) == PRELUDE_REDRAWS + 1
    (failure,) = report["tasks"]["open_drawer"]["failures"]
    assert failure["reason"].startswith("prelude: no task can run")


@pytest.mark.parametrize("value", [-1, 5, True])
def test_bad_evaluate_preludes_name_the_field(value):
    from trivla_drake.eval.evaluate import EvalConfig

    with pytest.raises(ValueError, match="prelude must be"):
        EvalConfig(tasks=["open_drawer"], episodes=1, prelude=value).validate()


def test_a_collection_resumed_with_other_settings_keeps_every_runs_settings(tmp_path):
    """meta/trivla_collection.json lists each run's settings where they changed (clean, then with preludes),
    so a folder holding both kinds says so; resuming with the same settings adds no entry."""
    import json

    from trivla_drake.eval.collect import PROGRESS_FILE, CollectConfig, collect

    out = tmp_path / "mixed"
    common = dict(out=str(out), tasks=["turn_off_light"], image_size=32)
    collect(CollectConfig(episodes_per_task=1, **common), progress=False)
    collect(CollectConfig(episodes_per_task=2, prelude_tasks=2, **common), progress=False)
    collect(CollectConfig(episodes_per_task=2, prelude_tasks=2, **common), progress=False)
    saved = json.loads((out / PROGRESS_FILE).read_text())
    assert [run["prelude_tasks"] for run in saved["runs"]] == [0, 2]
    assert [run["episodes_per_task"] for run in saved["runs"]] == [1, 2] and saved["config"]["prelude_tasks"] == 2
