"""The evaluation harness: report format, random baseline, bad input, failures (parallel = serial: test_rollout_runner.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from trivla_drake.eval import episode as episode_module
from trivla_drake.eval.cli_commands import main
from trivla_drake.eval.env import SimulationError, TabletopEnv
from trivla_drake.eval.episode import run_episode
from trivla_drake.eval.evaluate import EvalConfig, evaluate, format_markdown
from trivla_drake.eval.policies import RandomPolicy, load_policy
from trivla_drake.tasks import TASK_NAMES
from trivla_drake.tasks.oracle import OraclePolicy


def test_oracle_report_has_rates_stderr_average_and_chains(capsys):
    code = main(
        ["evaluate", "--policy", "oracle", "--tasks", "turn_on_light,open_drawer", "--episodes", "1",
         "--chains", "1", "--json", "--no-progress"]
    )
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert set(report["tasks"]) == {"turn_on_light", "open_drawer"}
    for row in report["tasks"].values():
        assert row["success_rate"] == 1.0 and row["stderr"] == 0.0 and row["episodes"] == 1
    assert report["average_success"] == 1.0
    assert report["chain_avg_len"] == 5.0
    table = format_markdown(report)
    assert "| turn_on_light | 1.000 | 0.000 | 1 |" in table and "Avg. Len" in table


def test_random_policy_fails():
    report = evaluate(
        EvalConfig(policy="random", tasks=["lift_block", "turn_on_light", "open_drawer"], episodes=1, max_steps=200),
        progress=False,
    )
    assert report["average_success"] == 0.0
    assert all("timeout" in row["failures"][0]["reason"] for row in report["tasks"].values())


def test_unknown_task_and_policy_are_clear_errors(capsys):
    assert main(["evaluate", "--tasks", "lift_block,dance", "--episodes", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "dance" in err and all(name in err for name in TASK_NAMES)
    with pytest.raises(ValueError, match="oracle, random"):
        load_policy("no/such/checkpoint")


def test_bad_thread_count_is_a_clear_error(capsys):
    assert main(["evaluate", "--tasks", "lift_block", "--episodes", "1", "--set", "threads=0", "--no-progress"]) == 2
    assert "threads must be at least 1" in capsys.readouterr().err


def test_a_directory_that_is_not_a_checkpoint_is_a_clear_error(tmp_path, capsys):
    assert main(["evaluate", "--policy", str(tmp_path), "--tasks", "lift_block", "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert "config.json" in err and str(tmp_path) in err


def test_a_failing_simulation_is_a_failure_with_its_reason(monkeypatch):
    original = TabletopEnv.step

    def failing_step(self, action, **kwargs):
        if self.step_index == 5:
            raise SimulationError("contact solver diverged (injected)")
        return original(self, action, **kwargs)

    monkeypatch.setattr(episode_module.TabletopEnv, "step", failing_step)
    result = run_episode("turn_on_light", 1, OraclePolicy())
    assert not result.success and "injected" in result.reason and result.steps == 5
    report = evaluate(EvalConfig(policy="oracle", tasks=["turn_on_light"], episodes=2), progress=False)
    assert report["tasks"]["turn_on_light"]["episodes"] == 2  # the run goes on
    assert all("SimulationError" in f["reason"] for f in report["tasks"]["turn_on_light"]["failures"])


def test_policy_chunks_and_bad_outputs(monkeypatch):
    calls = []

    class Chunky(RandomPolicy):
        def act(self, observation):
            calls.append(observation["time"])
            return np.zeros((10, 7))

    result = run_episode("lift_block", 2, Chunky(), max_steps=30)
    assert not result.success and len(calls) == 3  # one call per chunk of 10

    class Broken(RandomPolicy):
        def act(self, observation):
            return np.zeros(5)

    result = run_episode("lift_block", 2, Broken(), max_steps=30)
    assert not result.success and "shape" in result.reason


def test_record_dir_saves_one_video_per_episode(tmp_path):
    from trivla_drake.data.video import read_video

    report = evaluate(
        EvalConfig(policy="random", tasks=["turn_on_light"], episodes=1, record_dir=str(tmp_path),
                   image_size=32, max_steps=20),
        progress=False,
    )
    assert report["tasks"]["turn_on_light"]["episodes"] == 1
    (video,) = tmp_path.glob("*.mp4")
    frames = read_video(video)
    assert frames.shape == (21, 32, 64, 3)  # static | wrist side by side, every step and the last state


def test_default_evaluation_scenes_are_unseen_by_default_collection():
    from trivla_drake.eval.collect import CollectConfig
    from trivla_drake.eval.episode import derive_seed
    from trivla_drake.eval.evaluate import EvalConfig
    from trivla_drake.eval.paper_tables import TablesConfig
    from trivla_drake.tasks import TASK_NAMES

    collected = {derive_seed(CollectConfig.seed, task, a) for task in TASK_NAMES for a in range(200)}
    for base in (EvalConfig.seed, *TablesConfig().seeds):
        assert base != CollectConfig.seed
        assert not collected & {derive_seed(base, task, i) for task in TASK_NAMES for i in range(50)}


class _ImageSpy:
    """Looks at the cameras at every chunk boundary (4-step chunks of small moves) and remembers what it saw."""

    name = "image-spy"
    uses_images = True
    privileged = False

    def __init__(self):
        self.seen = []

    def reset(self, instruction, seed):
        pass

    def act(self, observation):
        self.seen.append((observation["time"], observation["static_rgb"].tobytes(), observation["wrist_rgb"].tobytes()))
        return np.tile([0.004, 0.0, -0.003, 0.0, 0.0, 0.0, 1.0], (4, 1))


def test_images_rendered_only_at_chunk_boundaries_are_those_of_every_step_rendering(tmp_path):
    lazy, every_step = _ImageSpy(), _ImageSpy()
    run_episode("lift_block", 3, lazy, image_size=64, max_steps=12)
    run_episode("lift_block", 3, every_step, image_size=64, max_steps=12, video_path=tmp_path / "all.mp4")
    assert len(lazy.seen) == 3 and [t for t, *_ in lazy.seen] == pytest.approx([0.0, 4 / 36, 8 / 36])
    assert lazy.seen == every_step.seen
    assert lazy.seen[0][2] != lazy.seen[2][2]  # the wrist camera moved with the hand


def test_chains_only_report_has_no_task_rows():
    """`evaluate --episodes 0 --chains N` (tasks default to all): no per-task rows and no average,
    rather than every task at 0.0 from zero episodes."""
    from trivla_drake.eval.evaluate import summarize

    config = EvalConfig(policy="oracle", tasks=list(TASK_NAMES), episodes=0, chains=2)
    first = ["open_drawer", "lift_block", "push_block_left"]
    second = ["close_drawer", "turn_on_light", "stack_block", "rotate_block_left", "unstack_block"]
    chains = [
        {"seed": 1, "completed": 2, "reason": "push_block_left: timeout", "subtasks": [{"task": t} for t in first]},
        {"seed": 2, "completed": 5, "reason": "", "subtasks": [{"task": t} for t in second]},
    ]
    report = summarize(config, [], chains)
    assert report["tasks"] == {} and report["average_success"] is None
    assert report["chain_avg_len"] == 3.5 and report["chains"]["completed_at_least"] == [1.0, 1.0, 0.5, 0.5, 0.5]
    assert report["chains"]["tasks"] == [first, second]
    positions = report["chains"]["by_position"]
    assert [(r["tried"], r["succeeded"]) for r in positions] == [(2, 2), (2, 2), (2, 1), (1, 1), (1, 1)]
    assert positions[2]["failed_tasks"] == ["push_block_left"]
    table = format_markdown(report)
    assert "average" not in table and "| 2 | 1.00 | 1.00 | 0.50 | 0.50 | 0.50 | 3.50 ± 1.50 |" in table
    assert "| succeeded / tried | 2 / 2 | 2 / 2 | 1 / 2 | 1 / 1 | 1 / 1 |" in table


def test_chains_take_evaluates_max_steps_as_single_episodes_do():
    """`evaluate --set max_steps=N --chains K`: every chain task gets N steps, so a capped run caps Avg. Len too."""
    config = EvalConfig(policy="oracle", tasks=[], chains=1, max_steps=3, seed=5)
    report = evaluate(config, progress=False)
    assert report["chain_avg_len"] == 0.0
    assert report["chains"]["failures"][0]["reason"].endswith("timeout: no success within 3 steps")
