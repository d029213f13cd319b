"""The `collect` and `evaluate` subcommands, for `trivla_drake.cli` to register:

    from trivla_drake.eval.cli_commands import add_collect_parser, add_evaluate_parser
    add_collect_parser(commands)    # commands = parser.add_subparsers(...)
    add_evaluate_parser(commands)

Each sets `run` to a function taking the parsed args and returning the exit code, like the other
subcommands. User errors (unknown task, not a dataset, bad numbers) print one line and return 2.
`python -m trivla_drake.eval.cli_commands collect|evaluate ...` runs them without cli.py.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from typing import Any

from trivla_drake.config_io import add_config_arguments
from trivla_drake.eval.evaluate_config import EVAL_BASE_SEED, parse_seeds
from trivla_drake.tasks.suite import TASK_NAMES


# The flags of `collect` and `evaluate`: config field -> flag (the other fields are set with --set or --config).
COLLECT_FLAGS = {"out": "--out", "episodes_per_task": "--episodes-per-task", "tasks": "--tasks", "seed": "--seed",
                 "workers": "--workers", "ray_address": "--ray-address"}
EVALUATE_FLAGS = {"policy": "--policy", "tasks": "--tasks", "episodes": "--episodes", "chains": "--chains",
                  "seed": "--seed", "seeds": "--seeds", "workers": "--workers", "ray_address": "--ray-address",
                  "paraphrases": "--paraphrases", "out": "--out"}
# `tables` (registered in cli.py): its TablesConfig fields' flags, and its checkpoints' (role -> flag).
TABLES_FLAGS = {"out": "--out", "episodes": "--episodes", "seeds": "--seeds", "workers": "--workers",
                "ray_address": "--ray-address"}
TABLES_CHECKPOINT_FLAGS = {"full": "--full", "system1_3": "--system1-3", "system1": "--system1", "data10": "--data10"}
# `sim`, `demo` and `bench` (registered in cli.py): their SimConfig, DemoConfig and BenchConfig fields' flags.
SIM_FLAGS = {"seconds": "--seconds", "meshcat": "--meshcat", "record": "--record"}
DEMO_FLAGS = {name: "--" + name for name in ("policy", "checkpoint", "preset", "task", "instruction", "episodes",
                                              "chains", "seed", "latency", "meshcat", "record")}
BENCH_FLAGS = {"model": "--model", "throughput": "--throughput", "preset": "--preset", "checkpoint": "--checkpoint"}


def flag_values(args: argparse.Namespace, flags: dict[str, str]) -> dict[str, Any]:
    """{field: the value its flag was given} (None where it was not given) for `with_flags`."""
    return {field: getattr(args, flag.lstrip("-").replace("-", "_")) for field, flag in flags.items()}


def command_config(schema: type, args: argparse.Namespace, flags: dict[str, Any], *,
                   finish: Callable[[Any], None] | None = None):
    """A command's config: its schema's defaults, then `--config FILE`, then the `--set` overrides in order, then the
    `flags` given (dotted field -> value, None: not given), then `finish(config)` (flags that are no one field).
    With `--print-config` the config is printed as YAML (what `--config` reads) and None returned: the command then
    runs nothing."""
    from trivla_drake.config_io import config_from_args, dump_config, with_flags

    config = with_flags(config_from_args(schema, args), flags)
    if finish is not None:
        finish(config)
    if args.print_config:
        print(dump_config(config), end="")
        return None
    return config


def add_ray_arguments(parser: argparse.ArgumentParser) -> None:
    """`--workers` and `--ray-address`, where a rollout command's episodes run (eval/rollout_runner.py)."""
    parser.add_argument("--workers", type=int, default=None,
                        help="worker processes on this machine (default 1: in this process; more: a local Ray)")
    parser.add_argument("--ray-address", default=None, metavar="ADDRESS",
                        help="run on an existing Ray cluster instead, e.g. ray://head:10001 or auto "
                             "(default: $RAY_ADDRESS if set)")


def _user_errors():
    from trivla_drake.data.lerobot_format import NotADatasetError

    # ScenarioError is a ValueError (naming it here would import Drake, which `main` reports missing).
    return (ValueError, NotADatasetError, FileNotFoundError, NotImplementedError)


def _task_list(text: str) -> list[str]:
    from trivla_drake.tasks.suite import parse_task_list

    return parse_task_list(text)


def run_collect(args: argparse.Namespace) -> int:
    """`trivla-drake collect`: oracle demonstrations -> LeRobot dataset."""
    from trivla_drake.eval.collect import CollectConfig, collect

    try:
        if args.tasks:
            args.tasks = _task_list(",".join(args.tasks))
        config = command_config(CollectConfig, args, flag_values(args, COLLECT_FLAGS))
        if config is None:
            return 0
        summary = collect(config, progress=not args.no_progress)
    except _user_errors() as error:
        print(f"trivla-drake collect: error: {error}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"| dataset | {summary['out']} |\n| --- | --- |")
        print(f"| episodes | {summary['episodes']} |\n| frames | {summary['frames']} |")
        for task, n in summary["per_task"].items():
            failed = summary["failed_attempts"].get(task, 0)
            print(f"| {task} | {n} episodes, {failed} failed attempts |")
    return 1 if summary["short_tasks"] else 0


def run_evaluate(args: argparse.Namespace) -> int:
    """`trivla-drake evaluate`: closed-loop success rates and chain Avg. Len."""
    from trivla_drake.eval.evaluate import EvalConfig, evaluate, format_markdown

    try:
        if args.tasks is not None:
            args.tasks = _task_list(args.tasks)
        if args.seeds is not None:
            if args.seed is not None:
                raise ValueError("give --seed or --seeds, not both")
            args.seeds = parse_seeds(args.seeds)
        config = command_config(EvalConfig, args, flag_values(args, EVALUATE_FLAGS))
        if config is None:
            return 0
        report = evaluate(config, progress=not args.no_progress)
    except _user_errors() as error:
        print(f"trivla-drake evaluate: error: {error}", file=sys.stderr)
        return 2
    print(json.dumps(report) if args.json else format_markdown(report))
    return 0


def add_collect_parser(commands) -> argparse.ArgumentParser:
    """Register `collect` on an argparse subparsers object."""
    parser = commands.add_parser(
        "collect", help="roll out the scripted oracle and write a LeRobot-format dataset (resumable); settings "
                        "beyond these flags: --set field=value (see --print-config), e.g. "
                        "--set perturbation.name=dart --set prelude_tasks=4",
    )
    parser.add_argument("--out", default=None, help="dataset folder (resumed if it holds an earlier run)")
    parser.add_argument("--episodes-per-task", type=int, default=None,
                        help="successful episodes per task (default 50)")
    parser.add_argument(
        "--tasks", nargs="+", default=None, metavar="TASK",
        help=f"tasks (default: all): {', '.join(TASK_NAMES)}; also accepts one comma-separated list",
    )
    parser.add_argument("--seed", type=int, default=None, help="base seed (default 0)")
    add_ray_arguments(parser)
    add_config_arguments(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="print one JSON summary on stdout")
    parser.set_defaults(run=run_collect)
    return parser


def add_evaluate_parser(commands) -> argparse.ArgumentParser:
    """Register `evaluate` on an argparse subparsers object."""
    parser = commands.add_parser(
        "evaluate", help="closed-loop evaluation: per-task success and chain Avg. Len; settings beyond these flags: "
                         "--set field=value (see --print-config), e.g. --set prelude=1 --set hold_check=0.5 "
                         "--set inference.execute_steps=5")
    parser.add_argument("--policy", default=None,
                        help="oracle (the default), random, trivla (the shipped checkpoint models/trivla_cpu) or a "
                             "checkpoint directory")
    parser.add_argument("--tasks", default=None, help=f"all (the default), or comma-separated names: "
                                                      f"{', '.join(TASK_NAMES)}")
    parser.add_argument("--episodes", type=int, default=None, help="episodes per task (default 10; 0: chains only)")
    parser.add_argument("--chains", type=int, default=None, help="chains of 5 tasks to run (default 0)")
    parser.add_argument("--seed", type=int, default=None,
                        help=f"base seed (default {EVAL_BASE_SEED}: scenes unseen by demonstrations collected "
                             "with seed 0)")
    parser.add_argument("--seeds", default=None, metavar="SEEDS",
                        help="several base seeds in one call, e.g. 1000-1017 or 1000,1001: each seed's figures and "
                             "the pooled ones")
    add_ray_arguments(parser)
    parser.add_argument("--paraphrases", action="store_true", default=None,
                        help="use held-out instruction paraphrases")
    parser.add_argument("--out", default=None, metavar="DIR",
                        help="also write the report as DIR/report.json, DIR/report.md and its plot DIR/report.png, and the "
                             "config as DIR/eval_config.yaml; "
                             "each result is kept in DIR/episodes.jsonl as it comes, so a killed run resumes and a "
                             "larger one (more chains, seeds, tasks) runs only what is missing")
    add_config_arguments(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    parser.set_defaults(run=run_evaluate)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Standalone entry point with just these two subcommands."""
    import logging

    parser = argparse.ArgumentParser(prog="trivla-drake")
    commands = parser.add_subparsers(dest="command", required=True)
    add_collect_parser(commands)
    add_evaluate_parser(commands)
    args = parser.parse_args(argv)
    logging.getLogger("drake").setLevel(logging.ERROR)
    return args.run(args)


if __name__ == "__main__":
    sys.exit(main())
