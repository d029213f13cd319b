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
import math
import sys
from pathlib import Path

from trivla_drake.eval.evaluate import EVAL_BASE_SEED
from trivla_drake.tasks.suite import TASK_NAMES


# Ports a Meshcat server can listen on (0: any free port).
PORTS = range(0, 65536)


def check_seconds(seconds: float | None, flag: str) -> float | None:
    """`seconds` if None (the default) or a finite time above 0; else ValueError naming `flag` (nan, inf and -1 would
    run forever or stop at once)."""
    if seconds is not None and not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"{flag} must be a finite number of seconds above 0, got {seconds}")
    return seconds


def check_port(port: int | None, flag: str = "--port") -> int | None:
    """`port` if None (Drake's default, 7000 up) or 0 to 65535 (0: any free port); else ValueError naming `flag`."""
    if port is not None and port not in PORTS:
        raise ValueError(f"{flag} must be a port from {PORTS.start} to {PORTS.stop - 1} (0: any free port), got {port}")
    return port


def check_record_path(path: str | None, flag: str = "--record") -> str | None:
    """`path` if None or where a recording's HTML file can be written; else ValueError naming `flag` (checked before
    a simulation runs, not when its recording is saved)."""
    if path is None:
        return None
    target = Path(path)
    if target.is_dir():
        raise ValueError(f"{flag} {path} is a folder: give a file name, e.g. {target / 'run.html'}")
    blocking = next((parent for parent in target.parents if parent.exists()), None)
    if blocking is not None and not blocking.is_dir():
        raise ValueError(f"{flag} {path}: {blocking} is a file, not a folder")
    return path


def check_instruction_text(text: str | None, flag: str = "--instruction") -> str | None:
    """`text` if None (the task's own) or a non-empty instruction that is valid text (a command-line argument in
    another encoding than UTF-8 arrives with its bad bytes as surrogates); else ValueError naming `flag`."""
    if text is None:
        return None
    try:
        text.encode("utf-8")
    except UnicodeEncodeError as error:
        bad = text[error.start:error.end].encode("utf-8", "backslashreplace").decode("ascii")
        raise ValueError(f"{flag} is not UTF-8 text ({bad} at character {error.start}: a byte that is not UTF-8); "
                         "give the instruction in UTF-8") from None
    if not text.strip():
        raise ValueError(f"{flag} is empty; give the task in words, e.g. 'pick up the red block' (or leave it out "
                         "for the task's own instruction)")
    return text


def _user_errors():
    from trivla_drake.data.lerobot import NotADatasetError

    # ScenarioError is a ValueError (naming it here would import Drake, which `main` reports missing).
    return (ValueError, NotADatasetError, FileNotFoundError, NotImplementedError)


def _task_list(text: str) -> list[str]:
    from trivla_drake.tasks.suite import parse_task_list

    return parse_task_list(text)


def run_collect(args: argparse.Namespace) -> int:
    """`trivla-drake collect`: oracle demonstrations -> LeRobot dataset."""
    from trivla_drake.eval.collect import CollectConfig, collect

    try:
        config = CollectConfig(
            out=args.out,
            episodes_per_task=args.episodes_per_task,
            tasks=_task_list(",".join(args.tasks) if args.tasks else "all"),
            seed=args.seed,
            workers=args.workers,
            image_size=args.image_size,
            action_noise=args.action_noise,
            prelude_tasks=args.prelude_tasks,
        )
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
        config = EvalConfig(
            policy=args.policy,
            tasks=_task_list(args.tasks) if args.episodes > 0 else [],
            episodes=args.episodes,
            seed=args.seed,
            chains=args.chains,
            paraphrases=args.paraphrases,
            workers=args.workers,
            record_dir=args.record_dir,
            image_size=args.image_size,
            max_steps=args.max_steps,
            noise_scale=args.noise_scale,
            execute_steps=args.execute_steps,
            ensemble_decay=args.ensemble_decay,
            prelude=args.prelude,
            policy_wrappers=["home_first"] if args.home_first else [],
            hold_check=args.hold_check,
        )
        if args.threads < 1:
            raise ValueError(f"--threads must be at least 1, got {args.threads}")
        import torch

        threads = torch.get_num_threads()
        torch.set_num_threads(args.threads)  # a serial run; each --workers process uses 1
        try:
            report = evaluate(config, progress=not args.no_progress)
        finally:
            torch.set_num_threads(threads)
    except _user_errors() as error:
        print(f"trivla-drake evaluate: error: {error}", file=sys.stderr)
        return 2
    print(json.dumps(report) if args.json else format_markdown(report))
    return 0


def add_collect_parser(commands) -> argparse.ArgumentParser:
    """Register `collect` on an argparse subparsers object."""
    parser = commands.add_parser(
        "collect", help="roll out the scripted oracle and write a LeRobot-format dataset (resumable)"
    )
    parser.add_argument("--out", required=True, help="dataset folder (resumed if it holds an earlier run)")
    parser.add_argument("--episodes-per-task", type=int, required=True, help="successful episodes per task")
    parser.add_argument(
        "--tasks", nargs="+", default=None, metavar="TASK",
        help=f"tasks (default: all): {', '.join(TASK_NAMES)}; also accepts one comma-separated list",
    )
    parser.add_argument("--seed", type=int, default=0, help="base seed (default 0)")
    parser.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument("--image-size", type=int, default=224, help="camera image size [px] (default 224)")
    parser.add_argument(
        "--action-noise", type=float, default=0.0,
        help="disturb the applied actions in short bursts, this many times the default burst rate "
             "(DART; 0 = clean demonstrations, the default; 1 = a burst about every 17 steps). The recorded "
             "actions stay the oracle's; episodes started from now on get this setting.",
    )
    parser.add_argument(
        "--prelude-tasks", type=int, default=0,
        help="before its task the oracle completes 1 to this many other tasks of a chain (drawn per episode, "
             "never a lift), unrecorded, so the episode starts where a chain's earlier tasks leave the scene "
             "and the hand (data for the later tasks of 5-task chains; default 0: from the start posture). "
             "Episodes started from now on get this setting.",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="print one JSON summary on stdout")
    parser.set_defaults(run=run_collect)
    return parser


def add_noise_scale_argument(parser: argparse.ArgumentParser) -> None:
    """--noise-scale: the inference setting of TriVLA's System 1 sampling (see EvalConfig.noise_scale)."""
    parser.add_argument("--noise-scale", type=float, default=None,
                        help="TriVLA: standard deviation of the noise System 1's flow-matching sampling starts "
                             "from (default 1, the paper's; 0: deterministic chunks)")


def add_chunk_execution_arguments(parser: argparse.ArgumentParser) -> None:
    """--execute-steps / --ensemble-decay: how TriVLA's action chunks are played (see EvalConfig)."""
    parser.add_argument("--execute-steps", type=int, default=None,
                        help="TriVLA: replan every this many control steps, playing the first rows of each "
                             "chunk (1 to 10; default 10, the whole chunk)")
    parser.add_argument("--ensemble-decay", type=float, default=None,
                        help="TriVLA: average the overlapping chunks that cover each step with weights "
                             "exp(-m i), i = 0 the oldest (ACT's temporal ensembling; default: play the newest; "
                             "with --execute-steps below the chunk length, since whole chunks do not overlap)")


def add_evaluate_parser(commands) -> argparse.ArgumentParser:
    """Register `evaluate` on an argparse subparsers object."""
    parser = commands.add_parser("evaluate", help="closed-loop evaluation: per-task success and chain Avg. Len")
    parser.add_argument("--policy", default="oracle",
                        help="oracle, random, trivla (the shipped checkpoint models/trivla_cpu) or a checkpoint directory")
    parser.add_argument("--tasks", default="all", help=f"all, or comma-separated names: {', '.join(TASK_NAMES)}")
    parser.add_argument("--episodes", type=int, default=10, help="episodes per task (default 10; 0: chains only)")
    parser.add_argument("--seed", type=int, default=EVAL_BASE_SEED,
                        help=f"base seed (default {EVAL_BASE_SEED}: scenes unseen by demonstrations collected "
                             "with seed 0)")
    parser.add_argument("--chains", type=int, default=0, help="chains of 5 tasks to run (default 0)")
    parser.add_argument("--paraphrases", action="store_true", help="use held-out instruction paraphrases")
    parser.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads of a serial run (default 1, like each worker process, so that "
                             "TriVLA's results do not depend on --workers)")
    parser.add_argument("--record-dir", default=None, help="save one mp4 per episode / chain here")
    parser.add_argument("--image-size", type=int, default=None, help="camera size for policies that look (224)")
    parser.add_argument("--max-steps", type=int, default=None, help="cap on steps per episode (default: per task)")
    add_noise_scale_argument(parser)
    add_chunk_execution_arguments(parser)
    parser.add_argument("--prelude", type=int, default=0,
                        help="start every episode after the oracle has completed this many other tasks of a chain "
                             "(unrecorded): the success of each task where a chain's later tasks start (default 0: "
                             "from the start posture; a prelude that fails is redrawn)")
    parser.add_argument("--home-first", action="store_true",
                        help="learned policies: at the start of every task that does not start the episode (a "
                             "chain's later tasks, a task after --prelude) the hand first goes back to the start "
                             "posture's pose, scripted, and the policy acts once the arm has settled there (or after "
                             "108 steps); those steps count against the task's")
    parser.add_argument("--hold-check", type=float, default=None, metavar="SECONDS",
                        help="after each success hold the hand still this long (the gripper keeping its last command) "
                             "and ask the task's predicate again; the report adds the successes that lasted, and "
                             "chains an Avg. Len of those (e.g. 0.5; default: none; successes still count when the "
                             "predicate first holds, as in CALVIN; a chain's next task starts after the hold, so the "
                             "chains themselves differ from runs without it)")
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
