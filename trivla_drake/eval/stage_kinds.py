"""The rollout jobs as recipe stage kinds (trivla_drake/recipe.py): "collect", "evaluate" and "tables", registered
when this module is imported. Each stage's config is the job's own (CollectConfig, EvalConfig, TablesConfig); a
stage is done when its output is complete for that very config, and describes itself as the equivalent command:

    - name: demos
      kind: collect
      config: {out: ${workdir}/data/demos, episodes_per_task: 30}
    # dry run: trivla-drake collect --out /abs/workdir/data/demos --episodes-per-task 30
"""

from __future__ import annotations

import dataclasses as dc
import json
import shlex
from pathlib import Path

from trivla_drake.config_io import describe_command
from trivla_drake.eval.cli_commands import COLLECT_FLAGS, EVALUATE_FLAGS, TABLES_CHECKPOINT_FLAGS, TABLES_FLAGS
from trivla_drake.eval.collect_config import CollectConfig
from trivla_drake.eval.evaluate_config import EvalConfig
from trivla_drake.eval.tables_config import TablesConfig
from trivla_drake.recipe import register_stage_kind


def collect_is_done(config: CollectConfig, workdir: str = "") -> bool:
    """The dataset at `config.out` holds `episodes_per_task` episodes of every task of `config`."""
    from trivla_drake.data.lerobot_format import EPISODE_TASK_KEY
    from trivla_drake.data.lerobot_reader import LeRobotReader

    if not (Path(config.out) / "meta" / "info.json").is_file():
        return False
    try:
        rows = LeRobotReader(config.out).episodes
    except (OSError, ValueError):
        return False
    counts = {task: 0 for task in config.tasks}
    for row in rows:
        if row.get(EPISODE_TASK_KEY) in counts:
            counts[row[EPISODE_TASK_KEY]] += 1
    return all(count >= config.episodes_per_task for count in counts.values())


def evaluate_is_done(config: EvalConfig, workdir: str = "") -> bool:
    """`config.out` holds report.json of this very config."""
    from trivla_drake.eval.evaluate import is_reported

    return is_reported(config)


def tables_is_done(config: TablesConfig, workdir: str = "") -> bool:
    """`config.out` holds report.json made with this very config."""
    from trivla_drake.eval.evaluate import report_has_config

    return bool(config.out) and report_has_config(Path(config.out) / "report.json", dc.asdict(config))


def describe_collect(config: CollectConfig) -> str:
    return describe_command("collect", config, COLLECT_FLAGS)


def describe_evaluate(config: EvalConfig) -> str:
    return describe_command("evaluate", config, EVALUATE_FLAGS)


def describe_tables(config: TablesConfig) -> str:
    checkpoints = [word for role, path in config.checkpoints.items() if role in TABLES_CHECKPOINT_FLAGS
                   for word in (TABLES_CHECKPOINT_FLAGS[role], path)]
    unflagged = {role: path for role, path in config.checkpoints.items() if role not in TABLES_CHECKPOINT_FLAGS}
    words = describe_command("tables", config, TABLES_FLAGS, leading=tuple(checkpoints), skip=("checkpoints",))
    return words + (f" --set {shlex.quote(f'checkpoints={json.dumps(unflagged)}')}" if unflagged else "")


def run_collect(config: CollectConfig, workdir: str = "") -> None:
    """Collects (or resumes collecting) the dataset."""
    from trivla_drake.eval.collect import collect

    collect(config)


def run_evaluate(config: EvalConfig, workdir: str = "") -> None:
    """Evaluates, writing OUT/report.json and OUT/eval_config.yaml."""
    from trivla_drake.eval.evaluate import evaluate

    if not config.out:
        raise ValueError("an evaluate stage needs out: the folder its report.json is written to")
    evaluate(config)


def run_tables(config: TablesConfig, workdir: str = "") -> None:
    """Makes the tables and writes them, with the config, into `config.out`."""
    import torch

    from trivla_drake.eval.paper_tables import make_tables, write_tables

    if not config.out:
        raise ValueError("a tables stage needs out: the folder its report is written to")
    threads = torch.get_num_threads()
    torch.set_num_threads(config.threads)
    try:
        write_tables(make_tables(config), config.out, config)
    finally:
        torch.set_num_threads(threads)


register_stage_kind("collect", CollectConfig, run=run_collect, is_done=collect_is_done, describe=describe_collect)
register_stage_kind("evaluate", EvalConfig, run=run_evaluate, is_done=evaluate_is_done, describe=describe_evaluate)
register_stage_kind("tables", TablesConfig, run=run_tables, is_done=tables_is_done, describe=describe_tables)
