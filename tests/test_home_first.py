"""The policy wrapper "home_first" (eval/home_first.py; `evaluate --set 'policy_wrappers=[{name: home_first}]'`): at the start of every task that does not start the episode the hand first
goes back to the start posture's pose, scripted, and once the arm has settled there the learned policy acts. The
homing reaches the pose within the action bounds, rises before it moves sideways, opens the hand unless it holds a
block, stops at its step budget, and runs again at every reset; bad settings are refused by name."""

from __future__ import annotations

import numpy as np
import pytest

from trivla_drake.eval.home_first import (
    ARRIVED_M,
    CHUNK_STEPS,
    SETTLE_STEPS,
    SETTLED_M,
    SETTLED_SPEED,
    HomeFirst,
    home_tcp_pose,
    homing_actions,
)
from trivla_drake.eval.plugin_config import PluginConfig
from trivla_drake.systems.action_executor import ACTION_HIGH, ACTION_LOW, apply_action, exp_so3

HOME_FIRST = PluginConfig("home_first")


def _away(home, dx=0.2, dy=-0.15, dz=-0.25, turn=(0.0, 0.0, 1.2)):
    X = home.copy()
    X[:3, 3] += (dx, dy, dz)
    X[:3, :3] = exp_so3(np.array(turn)) @ home[:3, :3]
    return X


def _observation(X, command=1.0, width=0.08, measured=None, joint_speed=0.0, time=1.0):
    """What the env observes: the commanded pose X, the measured one (X unless given), the fingers' width,
    the arm's joint speeds (all seven at `joint_speed`) and the simulated time [s] (0: the episode's start)."""
    state = np.zeros(18)
    state[7] = state[8] = width / 2
    state[9:16] = joint_speed
    return {"ee_target": X, "gripper_command": command, "state": state, "time": time,
            "tcp_pose": X if measured is None else measured}


def _integrate(X, rows):
    path = [X]
    for row in rows:
        X, _ = apply_action(X, row)
        path.append(X)
    return path


class Holding:
    """A learned-looking policy that holds its pose: zeros, gripper open; counts its calls."""

    name, uses_images, privileged = "holding", False, False

    def __init__(self):
        self.resets, self.calls = [], 0

    def reset(self, instruction, seed):
        self.resets.append(instruction)

    def act(self, observation):
        self.calls += 1
        return np.tile([0, 0, 0, 0, 0, 0, 1.0], (4, 1))


def test_homing_reaches_the_start_pose_within_the_bounds_rising_first_and_keeping_the_gripper():
    home = home_tcp_pose()
    start = _away(home)
    rows = homing_actions(start, home, -1.0, 500)
    assert 0 < len(rows) < 100
    assert np.all(rows >= ACTION_LOW - 1e-12) and np.all(rows <= ACTION_HIGH + 1e-12)
    assert np.all(rows[:, 6] == -1.0)  # a held block stays held
    path = _integrate(start, rows)
    assert np.linalg.norm(path[-1][:3, 3] - home[:3, 3]) < ARRIVED_M
    np.testing.assert_allclose(path[-1][:3, :3], home[:3, :3], atol=0.03)
    # Below the home height it goes straight up before anything else.
    rising = [i for i, X in enumerate(path[:-1]) if X[2, 3] < home[2, 3] - 0.02]
    assert rising and np.all(np.abs(rows[rising, :2]) < 1e-9) and np.all(np.abs(rows[rising, 3:6]) < 1e-9)
    assert homing_actions(home, home, 1.0, 10).shape == (0, 7)


def test_the_wrapper_homes_at_every_reset_then_hands_over_within_its_budget():
    home = home_tcp_pose()
    inner = Holding()
    policy = HomeFirst(inner)
    assert policy.name == "holding+home" and not policy.uses_images
    policy.reset("lift the red block", 0)
    X, steps = _away(home), 0
    while True:
        rows = policy.act(_observation(X))
        if inner.calls:
            break
        steps += len(rows)
        X = _integrate(X, rows)[-1]
    assert 0 < steps <= policy.max_steps
    assert np.linalg.norm(X[:3, 3] - home[:3, 3]) < ARRIVED_M
    # The next task homes again, and a short budget hands over when it is spent.
    short = HomeFirst(Holding(), max_steps=5)
    short.reset("open the drawer", 1)
    assert len(short.act(_observation(_away(home)))) == 5
    short.act(_observation(_away(home)))
    assert short.policy.calls == 1 and short.policy.resets == ["open the drawer"]
    short.reset("close the drawer", 2)
    assert len(short.act(_observation(_away(home)))) == 5
    assert short.policy.calls == 1


def test_the_hand_opens_unless_it_holds_a_block_and_waits_at_home_for_the_fingers():
    home = home_tcp_pose()
    for command, width, expected in ((1.0, 0.08, 1.0), (-1.0, 0.0, 1.0), (-1.0, 0.045, -1.0)):
        policy = HomeFirst(Holding())
        policy.reset("lift the red block", 0)
        assert np.all(policy.act(_observation(_away(home), command, width))[:, 6] == expected)
    at_home = HomeFirst(Holding())
    at_home.reset("lift the red block", 0)
    rows = at_home.act(_observation(home, -1.0, 0.0))  # home already, closed on nothing: open, wait
    assert len(rows) > 0 and np.all(rows[:, :6] == 0) and np.all(rows[:, 6] == 1.0)
    at_home.act(_observation(home, 1.0, 0.08))  # open now: the policy acts
    assert at_home.policy.calls == 1


def test_it_holds_the_commanded_home_until_the_measured_arm_is_there_and_still():
    home = home_tcp_pose()
    policy = HomeFirst(Holding())
    policy.reset("lift the red block", 0)
    lagging = _away(home, dx=0.08, dy=0.0, dz=0.0, turn=(0.0, 0.0, 0.0))
    for measured, speed in ((lagging, 0.0), (home, 0.5)):  # commanded home, the arm behind or still moving
        rows = policy.act(_observation(home, measured=measured, joint_speed=speed))
        assert len(rows) == SETTLE_STEPS and np.all(rows[:, :6] == 0) and np.all(rows[:, 6] == 1.0)
        assert policy.policy.calls == 0
    near = home.copy()
    near[0, 3] += 0.5 * SETTLED_M
    policy.act(_observation(home, measured=near, joint_speed=0.5 * SETTLED_SPEED / np.sqrt(7)))
    assert policy.policy.calls == 1
    # The first version (kept to reproduce research/home_first/) handed over with the arm still on its way.
    first = HomeFirst(Holding(), settle=False)
    first.reset("lift the red block", 0)
    first.act(_observation(home, measured=lagging, joint_speed=0.5, time=0.0))
    assert first.policy.calls == 1
    first.reset("lift the red block", 0)  # and it homed at the episode's start too
    assert len(first.act(_observation(_away(home), time=0.0))) == CHUNK_STEPS and first.policy.calls == 1
    # A held block stays held while it waits.
    holding = HomeFirst(Holding())
    holding.reset("put the red block in the bowl", 0)
    rows = holding.act(_observation(home, -1.0, 0.045, measured=lagging))
    assert len(rows) == SETTLE_STEPS and np.all(rows[:, 6] == -1.0)


def test_a_task_that_starts_the_episode_is_not_homed():
    home = home_tcp_pose()
    policy = HomeFirst(Holding())
    policy.reset("lift the red block", 0)
    policy.act(_observation(_away(home), time=0.0))  # a single task, or a chain's first: its start posture
    assert policy.policy.calls == 1
    policy.reset("put the red block in the bowl", 1)  # the chain's next task homes
    rows = policy.act(_observation(_away(home), time=4.2))
    assert policy.policy.calls == 1 and len(rows) == CHUNK_STEPS


class FirstLook(Holding):
    """Holding, and keeps the observation it is first called with (the state the policy takes over in)."""

    def act(self, observation):
        if not self.calls:
            self.first = {key: np.array(observation[key]) for key in ("tcp_pose", "state")}
        return super().act(observation)


def test_in_the_simulator_a_later_task_starts_from_the_start_pose():
    from trivla_drake.eval.episode import run_episode
    from trivla_drake.eval.episode_starts import make_episode_start

    inner = FirstLook()
    result = run_episode("turn_on_light", 123, HomeFirst(inner), keep_trajectory=True,
                         start=make_episode_start("chain_prelude", tasks=1), max_steps=110)
    assert len(result.prelude) == 1, result.reason
    tcp = np.asarray(result.trajectory.tcp_poses)
    home = home_tcp_pose()
    assert np.linalg.norm(tcp[0][:3] - home[:3, 3]) > 0.05  # the prelude left the hand elsewhere
    assert np.linalg.norm(tcp[-1][:3] - home[:3, 3]) < 0.015  # measured, after the homing and a hold
    # When the policy takes over the measured arm is at home and all but still (not catching up on the
    # commanded path, up to some 13 cm behind it: the first version's hand-over).
    assert inner.calls > 0, "the homing used up the whole budget"
    assert np.linalg.norm(inner.first["tcp_pose"][:3, 3] - home[:3, 3]) < SETTLED_M
    assert np.linalg.norm(inner.first["state"][9:16]) <= SETTLED_SPEED


def test_bad_settings_are_refused_by_name():
    from trivla_drake.eval.evaluate import EvalConfig
    from trivla_drake.tasks.oracle import OraclePolicy

    with pytest.raises(ValueError, match="max_steps"):
        HomeFirst(Holding(), max_steps=0)
    with pytest.raises(ValueError, match="oracle"):
        HomeFirst(OraclePolicy())
    with pytest.raises(ValueError, match="policy_wrappers: home_first applies to learned policies"):
        EvalConfig(policy="oracle", tasks=["lift_block"], episodes=1, policy_wrappers=[HOME_FIRST]).validate()


def test_the_config_field_wraps_the_policy_and_refuses_the_oracle(capsys):
    from trivla_drake.cli import main
    from trivla_drake.eval.evaluate import EvalConfig, _policy

    assert main(["evaluate", "--policy", "oracle", "--tasks", "lift_block", "--episodes", "1", "--set",
                 "policy_wrappers=[{name: home_first}]", "--no-progress"]) == 2
    assert "home_first applies to learned policies" in capsys.readouterr().err
    config = EvalConfig(policy="random", tasks=["lift_block"], episodes=1, policy_wrappers=[HOME_FIRST])
    wrapped = _policy(*config.policy_key())
    assert isinstance(wrapped, HomeFirst) and wrapped.name == "random+home"
    assert not isinstance(_policy("random"), HomeFirst)


def test_home_first_is_a_registered_policy_wrapper_and_unknown_wrappers_are_named():
    """The wrapper list of `evaluate` names registered policy wrappers; an unknown one is refused listing them."""
    from trivla_drake.eval.evaluate import EvalConfig
    from trivla_drake.eval.policies import load_policy
    from trivla_drake.eval.policy_wrappers import POLICY_WRAPPERS, wrap_policy

    assert "home_first" in POLICY_WRAPPERS.names()
    wrapped = wrap_policy(load_policy("random"), [HOME_FIRST])
    assert isinstance(wrapped, HomeFirst) and wrapped.name == "random+home"
    assert wrap_policy(wrapped, []) is wrapped
    with pytest.raises(ValueError, match="settings of the policy wrapper 'home_first': .*'steps'"):
        wrap_policy(load_policy("random"), [PluginConfig("home_first", {"steps": 3})])
    with pytest.raises(ValueError, match=r"policy_wrappers\[0\].name: unknown policy wrapper 'home_frist'; registered: "
                                         r"home_first"):
        EvalConfig(policy="random", tasks=["lift_block"], episodes=1,
                   policy_wrappers=[PluginConfig("home_frist")]).validate()
