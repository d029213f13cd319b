"""The rollout jobs as recipe stage kinds (eval/stage_kinds.py): each is done only when its output is complete for
that very config, and describes itself as a `trivla-drake` command that, parsed back, gives the same config."""

from __future__ import annotations

import contextlib
import io
import json
import shlex

import pytest

from trivla_drake.config_io import load_config
from trivla_drake.eval import stage_kinds
from trivla_drake.eval.collect_config import CollectConfig
from trivla_drake.eval.evaluate_config import EvalConfig
from trivla_drake.eval.inference_config import InferenceConfig
from trivla_drake.eval.plugin_config import PluginConfig
from trivla_drake.eval.tables_config import TablesConfig
from trivla_drake.recipe import registered_stage_kinds


def _printed_config(schema, command: str):
    """The config `command` (a described `trivla-drake ...` line) runs, read back from its --print-config."""
    from trivla_drake.cli import main

    words = shlex.split(command)
    assert words[0] == "trivla-drake"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        assert main([*words[1:], "--print-config"]) == 0
    return _from_yaml(schema, stdout.getvalue())


def _from_yaml(schema, text: str):
    import tempfile

    with tempfile.NamedTemporaryFile("w", suffix=".yaml") as f:
        f.write(text)
        f.flush()
        return load_config(schema, f.name)


CONFIGS = [
    CollectConfig(out="/w/data sim", episodes_per_task=60, tasks=["lift_block", "open_drawer"], workers=2,
                  perturbation=PluginConfig("dart", {"scale": 1.0}), prelude_tasks=4),
    CollectConfig(out="d"),
    EvalConfig(policy="trivla", tasks=["lift_block"], episodes=2, seed=1003, chains=20, out="/w/e", prelude=1,
               paraphrases=True, hold_check=0.5, policy_wrappers=[PluginConfig("home_first")],
               inference=InferenceConfig(execute_steps=5, ensemble_decay=0.1)),
    EvalConfig(episodes=0, chains=3, out="e"),
    TablesConfig(checkpoints={"full": "models/trivla_cpu", "system1": "runs/s1"}, out="o", chains=3,
                 seeds=[1000, 1001], workers=2, latency_tasks=["rotate_block_left", "turn_off_light"],
                 results_dir="results/evaluations"),
]


def test_the_three_kinds_are_registered():
    assert {"collect", "evaluate", "tables"} <= set(registered_stage_kinds())


@pytest.mark.parametrize("config", CONFIGS, ids=lambda c: type(c).__name__)
def test_describe_is_a_command_that_runs_the_same_config(config):
    describe = {CollectConfig: stage_kinds.describe_collect, EvalConfig: stage_kinds.describe_evaluate,
                TablesConfig: stage_kinds.describe_tables}[type(config)]
    command = describe(config)
    assert _printed_config(type(config), command) == config, command


def test_described_commands_use_the_flags_and_set_only_what_differs():
    assert stage_kinds.describe_collect(CollectConfig(out="d", episodes_per_task=20)) == \
        "trivla-drake collect --out d --episodes-per-task 20"
    assert stage_kinds.describe_evaluate(CONFIGS[2]).startswith(
        "trivla-drake evaluate --policy trivla --tasks lift_block --episodes 2 --seed 1003 --chains 20 --paraphrases "
        "--out /w/e --set inference.execute_steps=5")


def _dataset(root, counts: dict[str, int]):
    from trivla_drake.data.lerobot_format import EPISODE_TASK_KEY, vector_feature
    from trivla_drake.data.lerobot_writer import LeRobotWriter

    import numpy as np

    writer = LeRobotWriter(root, fps=36.0, features={"observation.state": vector_feature(["s"]),
                                                     "action": vector_feature(["a"])})
    for task, n in counts.items():
        for _ in range(n):
            writer.add_episode({"observation.state": np.zeros((3, 1), np.float32),
                                "action": np.zeros((3, 1), np.float32)}, task, extra={EPISODE_TASK_KEY: task})


def test_collect_is_done_when_every_task_has_its_episodes(tmp_path):
    config = CollectConfig(out=str(tmp_path / "ds"), episodes_per_task=2, tasks=["lift_block", "open_drawer"])
    assert not stage_kinds.collect_is_done(config)  # nothing there
    _dataset(tmp_path / "ds", {"lift_block": 2, "open_drawer": 1})
    assert not stage_kinds.collect_is_done(config)
    _dataset(tmp_path / "ds", {"open_drawer": 1})
    assert stage_kinds.collect_is_done(config)
    config.episodes_per_task = 3  # the recipe asks for more: resume
    assert not stage_kinds.collect_is_done(config)


def test_evaluate_is_done_only_for_its_own_report(tmp_path):
    from trivla_drake.eval.evaluate import summarize, write_report

    config = EvalConfig(tasks=["lift_block"], episodes=1, out=str(tmp_path / "e"))
    assert not stage_kinds.evaluate_is_done(config)
    episodes = [{"task": "lift_block", "success": True, "seed": 1, "instruction": "", "reason": ""}]
    files = write_report(config, summarize(config, episodes, []))
    assert stage_kinds.evaluate_is_done(config)
    assert load_config(EvalConfig, files["config"]) == config  # eval_config.yaml reads back as the config
    other = load_config(EvalConfig, files["config"], ["seed=1001"])
    assert not stage_kinds.evaluate_is_done(other)
    assert not stage_kinds.evaluate_is_done(EvalConfig(tasks=["lift_block"], episodes=1))  # no out
    (tmp_path / "e" / "report.json").write_text("{not json")
    assert not stage_kinds.evaluate_is_done(config)


def test_tables_is_done_only_for_its_own_report(tmp_path):
    config = TablesConfig(checkpoints={"full": "m"}, out=str(tmp_path / "t"))
    assert not stage_kinds.tables_is_done(config)
    (tmp_path / "t").mkdir()
    import dataclasses

    (tmp_path / "t" / "report.json").write_text(json.dumps({"config": dataclasses.asdict(config)}))
    assert stage_kinds.tables_is_done(config)
    config.chains = 3
    assert not stage_kinds.tables_is_done(config)


def test_a_stage_without_out_is_refused_naming_it():
    with pytest.raises(ValueError, match="evaluate stage needs out"):
        stage_kinds.run_evaluate(EvalConfig(tasks=["lift_block"], episodes=1))
    with pytest.raises(ValueError, match="tables stage needs out"):
        stage_kinds.run_tables(TablesConfig(checkpoints={"full": "m"}))
