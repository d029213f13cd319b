"""Policy takeovers (`collect --takeover CHECKPOINT`): a learned policy drives first, for a drawn number
of steps or until it commands the gripper closed (that close is not applied); then the expert takes
over from where it left the hand. With `resume_descent`, a hand left low near its grasp goes on down
from there (aligning first) instead of rising back. The policy's steps are recorded as disturbed, so
only the expert's own answer (row 0) of those frames is a label. Undisturbed, `resume_descent` changes
nothing; bad settings name the flag."""

from __future__ import annotations

import numpy as np
import pytest

from trivla_drake.data.lerobot import PERTURBED_FRAMES_KEY, TAKEOVER_KEY, LeRobotReader
from trivla_drake.data.samples import TrainingSamples
from trivla_drake.eval import policy_takeover
from trivla_drake.eval.policy_takeover import PolicyTakeover

EXPERT = np.array([0.0, 0.0, -0.003, 0.0, 0.0, 0.0, 1.0])
OBS = {"static_rgb": 0, "wrist_rgb": 0, "state": 0, "instruction": "lift the red block"}


class ScriptedPolicy:
    """Stands in for the learned policy: chunks of `rows`, and what it was reset with."""

    def __init__(self, rows):
        self.rows, self.resets, self.calls = np.asarray(rows, dtype=float), [], 0

    def reset(self, instruction, seed):
        self.resets.append(instruction)

    def act(self, observation):
        self.calls += 1
        return self.rows


@pytest.fixture
def checkpoint_dir(tmp_path):
    (tmp_path / "config.json").write_text("{}")
    return str(tmp_path)


def _takeover(monkeypatch, checkpoint_dir, rows, steps):
    policy = ScriptedPolicy(rows)
    monkeypatch.setattr(policy_takeover, "_harness_policy", lambda checkpoint, execute_steps: policy)
    return PolicyTakeover(checkpoint_dir, steps=steps).start(np.random.default_rng(0)), policy


def test_the_policy_drives_its_drawn_steps_then_the_expert_has_the_hand(monkeypatch, checkpoint_dir):
    move = [[0.002, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]] * 4
    state, policy = _takeover(monkeypatch, checkpoint_dir, move, (7, 7))
    out = [state.apply(EXPERT, OBS) for _ in range(12)]
    assert [flag for _, flag in out] == [True] * 7 + [False] * 5
    for applied, _ in out[:7]:
        np.testing.assert_array_equal(applied, move[0])  # the policy's rows, chunk after chunk
    for applied, _ in out[7:]:
        np.testing.assert_array_equal(applied, EXPERT)
    assert policy.resets == ["lift the red block"] and policy.calls == 2
    assert (state.driven, state.reason) == (7, "steps")


def test_the_policys_close_is_not_applied_the_expert_takes_over_there(monkeypatch, checkpoint_dir):
    rows = [[0.0, 0.0, -0.003, 0.0, 0.0, 0.0, 1.0]] * 3 + [[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0]]
    state, _ = _takeover(monkeypatch, checkpoint_dir, rows, (50, 50))
    out = [state.apply(EXPERT, OBS) for _ in range(6)]
    assert [flag for _, flag in out] == [True, True, True, False, False, False]
    assert all(applied[6] > 0.0 for applied, _ in out)  # the hand never closes on the policy's word
    np.testing.assert_array_equal(out[3][0], EXPERT)
    assert (state.driven, state.reason) == (3, "close")


def test_the_takeover_needs_what_the_policy_reads(monkeypatch, checkpoint_dir):
    state, _ = _takeover(monkeypatch, checkpoint_dir, [EXPERT], (5, 5))
    with pytest.raises(ValueError, match=r"static_rgb.*collect with cameras"):
        state.apply(EXPERT, {"ee_target": np.eye(4)})


def test_bad_takeover_settings_name_the_flag(tmp_path, checkpoint_dir):
    with pytest.raises(ValueError, match=r"--takeover: .* \(no config.json there\)"):
        PolicyTakeover(str(tmp_path / "missing"))
    with pytest.raises(ValueError, match="steps"):
        PolicyTakeover(checkpoint_dir, steps=(0, 5))
    with pytest.raises(ValueError, match="steps"):
        PolicyTakeover(checkpoint_dir, steps=(9, 5))


def test_takeover_cannot_be_combined_with_other_disturbances(checkpoint_dir):
    from trivla_drake.eval.collect import CollectConfig

    with pytest.raises(ValueError, match="--approach-drifts and --takeover"):
        CollectConfig(out="unused", episodes_per_task=1, approach_drifts=True, takeover=checkpoint_dir).validate()
    with pytest.raises(ValueError, match="--takeover"):
        CollectConfig(out="unused", episodes_per_task=1, takeover="no/such/folder").validate()


@pytest.mark.parametrize("task", ["lift_block", "stack_block", "place_in_bowl", "rotate_block_left", "unstack_block",
                                  "open_drawer"])
def test_resume_descent_changes_nothing_without_a_disturbance(task):
    from trivla_drake.eval.episode import run_episode
    from trivla_drake.tasks.oracle import OraclePolicy

    runs = [run_episode(task, 5, OraclePolicy(align_first=True, resume_descent=flag), keep_trajectory=True)
            for flag in (False, True)]
    assert all(r.success for r in runs)
    np.testing.assert_array_equal(np.stack(runs[0].trajectory.actions), np.stack(runs[1].trajectory.actions))


class OffCentreApproach:
    """A policy that takes the open hand down to 2.5 cm beside the named block at `height`, then closes."""

    def __init__(self, height):
        self.height = height

    def reset(self, instruction, seed):
        pass

    def act(self, observation):
        scene, task = observation["privileged"]["scene"], observation["privileged"]["task"]
        target = scene.block_position(task.params[0]) + np.array([0.025, 0.0, 0.0])
        target[2] = self.height
        d = target - np.asarray(observation["ee_target"])[:3, 3]
        row = np.zeros(7)
        row[6] = 1.0 if np.linalg.norm(d) > 1e-4 else -1.0
        row[:3] = d if np.linalg.norm(d) <= 0.004 else d * 0.004 / np.linalg.norm(d)
        return row[None]


@pytest.mark.parametrize(("resume", "height", "first_move"),
                         [(True, 0.07, "across"), (False, 0.07, "up"), (True, 0.045, "up")])
def test_the_expert_goes_on_from_where_the_policy_left_the_hand(monkeypatch, checkpoint_dir, resume, height,
                                                               first_move):
    """At 7 cm the hand is in the funnel above the grasp: the expert aligns across at that height (with
    `resume_descent`) or rises back to the leg above the block (without). At 4.5 cm it came down through
    the funnel and below it: the expert rises first."""
    from trivla_drake.eval.episode import run_episode
    from trivla_drake.tasks.oracle import ALIGN_FIRST_M, RESUME_ABOVE_M, OraclePolicy

    monkeypatch.setattr(policy_takeover, "_harness_policy", lambda checkpoint, execute_steps: OffCentreApproach(height))
    expert = OraclePolicy(align_first=True, resume_descent=resume)
    takeover = PolicyTakeover(checkpoint_dir, steps=(400, 400), expert=expert)
    result = run_episode("lift_block", 5, expert, image_size=32, keep_trajectory=True, action_noise=takeover)
    assert result.success, result.reason
    trajectory = result.trajectory
    driven = int(np.sum(trajectory.perturbed))
    assert trajectory.perturbed[:driven] == [True] * driven and not any(trajectory.perturbed[driven:])
    tcp = np.stack(trajectory.tcp_poses)[:, :3]
    actions = np.stack(trajectory.actions)
    first = actions[driven]  # the expert's first action of its own
    assert tcp[driven, 2] < height + 0.01  # the policy left the hand low, beside the block
    closed = int(np.flatnonzero(actions[:, 6] <= 0.0)[0])
    if first_move == "across":  # at that height, towards the block
        assert first[2] == 0.0 and first[:2] @ (tcp[closed, :2] - tcp[driven, :2]) > 0.0
        assert np.linalg.norm(tcp[closed, :2] - tcp[driven, :2]) > 0.02 - 2 * ALIGN_FIRST_M
    else:
        assert first[2] > 0.0
    if resume and first_move == "up":  # it rises only into the funnel, then aligns at that height
        level = int(np.flatnonzero(actions[driven:closed, 2] == 0.0)[0]) + driven
        grasp_z = tcp[closed, 2]
        assert RESUME_ABOVE_M - 0.01 < tcp[level, 2] - grasp_z < RESUME_ABOVE_M + 0.03


class Expert:
    def __init__(self):
        self.replans = 0

    def replan(self):
        self.replans += 1


@pytest.mark.parametrize("rows", [[[0.002, 0, 0, 0, 0, 0, 1.0]], [[0.0, 0, 0, 0, 0, 0, -1.0]]])
def test_the_expert_is_told_to_plan_again_once_when_the_policy_hands_back(monkeypatch, checkpoint_dir, rows):
    expert = Expert()
    monkeypatch.setattr(policy_takeover, "_harness_policy", lambda checkpoint, execute_steps: ScriptedPolicy(rows))
    state = PolicyTakeover(checkpoint_dir, steps=(3, 3), expert=expert).start(np.random.default_rng(0))
    for _ in range(8):
        state.apply(EXPERT, OBS)
    assert expert.replans == 1 and state.handed_back


def test_replan_plans_the_task_again_from_the_scene_as_it_is():
    from dataclasses import replace

    from trivla_drake.eval.episode import shared_env
    from trivla_drake.tasks.oracle import OraclePolicy
    from trivla_drake.tasks.suite import get_task, sample_task_instance

    env = shared_env(None)
    spec, instance = sample_task_instance(get_task("lift_block"), np.random.default_rng(5), env.layout())
    obs = env.reset(spec)
    scene = env.scene()
    expert = OraclePolicy(align_first=True, resume_descent=True)
    expert.reset(instance.instruction, 0)
    expert.act({**obs, "privileged": {"scene": scene, "task": instance}})
    color = instance.params[0]
    blocks = dict(scene.blocks)
    blocks[color] = blocks[color].copy()
    blocks[color][0, 3] += 0.03  # the policy pushed the block 3 cm
    pushed = replace(scene, blocks=blocks)

    def grasp_xy():
        return next(wp for wp in expert.plan if wp.turn_first).pose[:2, 3]

    expert.act({**obs, "privileged": {"scene": pushed, "task": instance}})
    np.testing.assert_allclose(grasp_xy(), scene.block_position(color)[:2])  # the plan stays
    expert.replan()
    expert.act({**obs, "privileged": {"scene": pushed, "task": instance}})
    np.testing.assert_allclose(grasp_xy(), pushed.block_position(color)[:2])


def test_a_checkpoint_that_does_not_load_fails_before_any_episode(tmp_path):
    from trivla_drake.eval.collect import CollectConfig

    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "config.json").write_text("{not json")
    with pytest.raises(ValueError, match="--takeover .*broken"):
        CollectConfig(out=str(tmp_path / "out"), episodes_per_task=1, takeover=str(broken)).validate()
    assert not (tmp_path / "out").exists()


def test_collect_records_the_takeover_and_masks_the_policys_later_rows(tmp_path, monkeypatch):
    from trivla_drake.eval.collect import CollectConfig, collect
    from trivla_drake.eval.trivla_harness_policy import TriVLAHarnessPolicy
    from trivla_drake.nn import TriVLA, make_config, save_checkpoint

    checkpoint = tmp_path / "tiny_policy"
    save_checkpoint(TriVLA(make_config("tiny"), load_pretrained=False), str(checkpoint))
    loaded = policy_takeover._harness_policy(str(checkpoint), None)
    assert isinstance(loaded, TriVLAHarnessPolicy)
    assert policy_takeover._harness_policy(str(checkpoint), 5).model is loaded.model  # loaded once per process

    class KeepsOpen:  # the untrained tiny model, with its hand kept open so that it drives all its steps
        def __init__(self, policy):
            self.policy = policy

        def reset(self, instruction, seed):
            self.policy.reset(instruction, seed)

        def act(self, observation):
            rows = np.array(self.policy.act(observation))
            rows[:, 6] = 1.0
            return rows

    monkeypatch.setattr(policy_takeover, "_harness_policy", lambda c, k: KeepsOpen(TriVLAHarnessPolicy(loaded.model)))
    out = tmp_path / "taken_over"
    config = CollectConfig(out=str(out), episodes_per_task=1, tasks=["lift_block"], takeover=str(checkpoint))
    short = PolicyTakeover(str(checkpoint), steps=(6, 6))
    config.disturbance = lambda: short  # a short takeover keeps the test fast (collect runs in this process)
    summary = collect(config, progress=False)
    assert summary["per_task"] == {"lift_block": 1}
    reader = LeRobotReader(out)
    episode = reader.episodes[0]
    assert episode[TAKEOVER_KEY] == "tiny_policy"
    assert episode[PERTURBED_FRAMES_KEY] == [0, 1, 2, 3, 4, 5]
    samples = TrainingSamples(out, cameras=[])
    assert not samples[0]["action_is_stale"][0] and samples[0]["action_is_stale"][1:].all()
    assert not samples[6]["action_is_stale"].any()
