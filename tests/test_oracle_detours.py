"""The oracle's detours (`collect --detours N`): before its task it visits places just above blocks the
instruction does not name, then still solves the task; the detours come from the episode's seed, and
collect records them per episode. Bad settings are refused naming the field."""

from __future__ import annotations

import numpy as np
import pytest

from trivla_drake.data.lerobot import DETOURS_KEY, LeRobotReader
from trivla_drake.eval.episode import run_episode
from trivla_drake.tasks import motions
from trivla_drake.tasks.oracle import OraclePolicy
from trivla_drake.tasks.scene import BLOCK_COLORS, BLOCK_HALF


def _first_close(result) -> int:
    actions = np.asarray(result.trajectory.actions).reshape(-1, 7)
    return int(np.flatnonzero(actions[:, 6] <= 0.0)[0])


def test_the_oracle_hovers_over_other_blocks_before_it_lifts_the_named_one():
    from trivla_drake.eval.episode import shared_env
    from trivla_drake.tasks.suite import get_task, sample_task_instance

    seed = 1000
    result = run_episode("lift_block", seed, OraclePolicy(detours=2), keep_trajectory=True)
    assert result.success, result.reason
    spec, instance = sample_task_instance(get_task("lift_block"), np.random.default_rng(seed), shared_env(None).layout())
    assert instance.instruction == result.instruction
    blocks = {c: np.asarray(b.position) for c, b in spec.blocks.items()}
    tcp = np.asarray(result.trajectory.tcp_poses)[: _first_close(result), :3]
    named = result.params[0]
    visited = [c for c, p in blocks.items() if c != named
               and ((np.linalg.norm(tcp[:, :2] - p[:2], axis=1) < 0.045) & (tcp[:, 2] < p[2] + 0.15)).any()]
    assert visited  # low above a block the instruction does not name, before the grasp
    plain = run_episode("lift_block", seed, OraclePolicy(), keep_trajectory=True)
    assert _first_close(plain) < len(tcp)  # the detours take time before the grasp


def test_detour_waypoints_avoid_the_named_block_and_follow_the_seed():
    from trivla_drake.eval.episode import shared_env
    from trivla_drake.tasks.suite import get_task, sample_task_instance

    env = shared_env(None)
    spec, instance = sample_task_instance(get_task("lift_block"), np.random.default_rng(3), env.layout())
    env.reset(spec)
    scene = env.scene()
    named = instance.params[0]
    plan = motions.detours(scene, named, np.random.default_rng(7), 6)
    assert len(plan) == 6 and all(wp.label == "detour" for wp in plan)
    for wp in plan:
        distances = {c: np.linalg.norm(wp.pose[:2, 3] - scene.block_position(c)[:2]) for c in BLOCK_COLORS}
        visited = min(distances, key=distances.get)
        assert visited != named and distances[visited] <= motions.DETOUR_JITTER * np.sqrt(2) + 1e-9
        top = scene.block_position(visited)[2] + BLOCK_HALF
        assert motions.DETOUR_CLEARANCE[0] <= wp.pose[2, 3] - top <= motions.DETOUR_CLEARANCE[1]
    again = motions.detours(scene, named, np.random.default_rng(7), 6)
    assert all(np.array_equal(a.pose, b.pose) for a, b in zip(plan, again))
    assert motions.detours(scene, named, np.random.default_rng(7), 0) == []
    with pytest.raises(ValueError, match="count must be >= 0"):
        motions.detours(scene, named, np.random.default_rng(7), -1)


def test_collect_records_the_detours_and_refuses_bad_counts(tmp_path):
    from trivla_drake.eval.collect import CollectConfig, collect

    out = tmp_path / "detours"
    summary = collect(CollectConfig(out=str(out), episodes_per_task=1, tasks=["lift_block"], image_size=32,
                                    detours=1), progress=False)
    assert summary["per_task"] == {"lift_block": 1}
    assert LeRobotReader(out).episodes[0][DETOURS_KEY] == 1
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="--detours must be an integer >= 0"):
            CollectConfig(out="unused", episodes_per_task=1, detours=bad).validate()
        with pytest.raises(ValueError, match="detours must be an integer >= 0"):
            OraclePolicy(detours=bad)
