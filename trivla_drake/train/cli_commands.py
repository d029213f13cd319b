"""The `train`, `export`, `soup` and `refit` subcommands, for `trivla_drake.cli` to register:

    from trivla_drake.train.cli_commands import add_train_parser
    add_train_parser(commands)      # commands = parser.add_subparsers(...)

    trivla-drake train --stage video  --data DEMOS --out runs/video
    trivla-drake train --stage vlm    --out runs/vlm    --init runs/video/final
    trivla-drake train --stage policy --data DEMOS --out runs/policy --init runs/vlm/final --set features.stride=3
    trivla-drake train --config runs/policy/train_config.yaml --print-config
    torchrun --nproc_per_node 2 -m trivla_drake.train.cli_commands train --stage policy ...

Each job's settings are its config dataclass (TrainConfig, ExportConfig, SoupConfig, RefitConfig): `--config FILE`
and `--set dotted.field=value` (read with Drake's typed YAML loader), then the few flags below. `--print-config`
prints the full config. A run returns the exit code (user errors print one line and return 2).
`python -m trivla_drake.train.cli_commands train ...` runs `train` without cli.py (and under torchrun).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from trivla_drake.config_io import add_config_arguments, config_from_args, dump_config, with_flags
from trivla_drake.train.config import STAGES, TrainConfig

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: no spinning OpenMP threads on shared cores

# TrainConfig's fields that `train` has a flag for (the rest go in --set); a `--no-...` flag sets its field false.
TRAIN_FLAGS = {"stage": "--stage", "out": "--out", "data": "--data", "init": "--init", "preset": "--preset",
               "steps": "--steps", "seed": "--seed", "resume": "--resume", "threads": "--threads",
               "progress": "--no-progress"}
# The flags `export`, `soup` and `refit` share (add_out_arguments).
JOB_FLAGS = {"out": "--out", "overwrite": "--overwrite"}


def _user_errors():
    from trivla_drake.data.lerobot_format import NotADatasetError

    return (ValueError, NotADatasetError, FileNotFoundError, FloatingPointError)


def train_config_from_args(args: argparse.Namespace) -> TrainConfig:
    """The TrainConfig the command line asks for: --config, then --set, then the direct flags."""
    return with_flags(config_from_args(TrainConfig, args), _flag_values(args, TRAIN_FLAGS))


def _flag_values(args: argparse.Namespace, flags: dict[str, str]) -> dict:
    """{field: the value its flag gave} (None where it was not given; a given `--no-...` flag: False) for
    `with_flags`."""
    values = {}
    for field, flag in flags.items():
        value = getattr(args, flag.lstrip("-").replace("-", "_"))
        values[field] = (not flag.startswith("--no-") if value else None) if isinstance(value, bool) else value
    return values


def _run_job(command: str, args: argparse.Namespace, make_config, run) -> int:
    """Reads the job's config (`make_config(args)`), prints it with --print-config, else `run(config)`; a user error
    (a config that does not fit, a bad setting) is one line on stderr and exit code 2."""
    try:
        config = make_config(args)
        if args.print_config:
            print(dump_config(config), end="")
            return 0
        return run(config)
    except _user_errors() as error:
        print(f"trivla-drake {command}: error: {error}", file=sys.stderr)
        return 2


def run_train(args: argparse.Namespace) -> int:
    """`trivla-drake train`: one training stage; prints the summary."""

    def run(config: TrainConfig) -> int:
        from trivla_drake.train.trainer import train

        summary = train(config)
        if int(os.environ.get("RANK", "0")) != 0:
            return 0
        if args.json:
            print(json.dumps(summary, default=str))
        else:
            print("| train | value |\n| --- | --- |")
            for key, value in summary.items():
                shown = f"{value:.4g}" if isinstance(value, float) else value
                print(f"| {key} | {shown} |")
        return 0

    return _run_job("train", args, train_config_from_args, run)


def add_train_parser(commands) -> argparse.ArgumentParser:
    """Register `train` on an argparse subparsers object."""
    parser = commands.add_parser(
        "train", help="train one TriVLA stage: video (System 3), vlm (System 2) or policy (System 1)",
        description="Train one stage. Run video, then vlm with --init VIDEO_OUT/final, then policy with "
                    "--init VLM_OUT/final. Under torchrun every process trains (DDP); rank 0 writes. Every setting "
                    "is a field of TrainConfig (trivla_drake/train/config.py): give them in a --config file or "
                    "with --set; --print-config shows them all. OUT/train_config.yaml holds a run's.",
    )
    parser.add_argument("--stage", default=None, choices=STAGES, help="what to train (field stage)")
    parser.add_argument("--data", default=None,
                        help="LeRobot dataset folder (video, policy); for vlm an optional folder for the "
                             "generated visual-question set")
    parser.add_argument("--out", default=None, help="run folder: checkpoints/, final/, log.jsonl, summary.json")
    parser.add_argument("--init", default=None, metavar="CHECKPOINT_DIR",
                        help="start from this checkpoint (the previous stage's final/); default: a fresh preset")
    parser.add_argument("--preset", default=None, help="model preset: tiny, cpu, paper (default: --init's, else cpu)")
    parser.add_argument("--steps", type=int, default=None, help="optimizer steps (default per stage: 3000/3000/10000)")
    parser.add_argument("--seed", type=int, default=None, help="seed of initialisation, data order and noise (0)")
    parser.add_argument("--resume", action="store_true", help="continue from the newest checkpoint in --out")
    parser.add_argument("--threads", type=int, default=None, help="torch threads per process (default: torch's)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    add_config_arguments(parser)
    parser.set_defaults(run=run_train)
    return parser


def _report_model_folder(target, what: str, dtype: str) -> int:
    """Prints the folder a job wrote and its size; exit code 0."""
    size = sum(p.stat().st_size for p in target.rglob("*") if p.is_file())
    print(f"wrote {target}{what} ({size / 1e6:.1f} MB, weights in {dtype})")
    return 0


def _add_job_parser(commands, name: str, run, config: str, settings: str, *, help: str,
                    example: str = "") -> argparse.ArgumentParser:
    """Register subcommand `name` (running `run`) whose settings beyond its flags are the fields of `config`."""
    parser = commands.add_parser(name, help=help, description=f"Settings ({settings}) are fields of {config}{example}; "
                                                              "--print-config shows them.")
    parser.set_defaults(run=run)
    return parser


def add_out_arguments(parser: argparse.ArgumentParser) -> None:
    """--out and --overwrite of `export`, `soup` and `refit`, and their --config/--set/--print-config."""
    parser.add_argument("--out", default=None,
                        help="folder to write; an earlier export there is replaced atomically once the new one is "
                             "complete, any other non-empty folder only with --overwrite")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace --out even when it holds other things than an earlier export (they are deleted; "
                             "never the working folder)")
    add_config_arguments(parser)


def _job_flags(args: argparse.Namespace) -> dict:
    return _flag_values(args, JOB_FLAGS)


def run_export(args: argparse.Namespace) -> int:
    """`trivla-drake export`: a checkpoint's model, without optimizer state, in a smaller dtype."""
    from trivla_drake.train.export_job import ExportConfig

    def run(config: ExportConfig) -> int:
        from trivla_drake.train.export_job import run_export as export

        return _report_model_folder(export(config), "", config.dtype)

    return _run_job("export", args, lambda args: with_flags(
        config_from_args(ExportConfig, args), {"checkpoint": args.checkpoint, **_job_flags(args)}), run)


def add_export_parser(commands) -> argparse.ArgumentParser:
    """Register `export` on an argparse subparsers object."""
    parser = _add_job_parser(
        commands, "export", run_export, "ExportConfig (trivla_drake/train/export_job.py)",
        "dtype, drop_unused_llm_layers",
        help="write a checkpoint's model (no optimizer state) with float16 weights, e.g. for models/trivla_cpu",
        example=": --set dtype=float32")
    parser.add_argument("checkpoint", help="checkpoint folder (a run's final/ or checkpoints/step-N/)")
    add_out_arguments(parser)
    return parser


def run_soup(args: argparse.Namespace) -> int:
    """`trivla-drake soup`: the uniform weight average of checkpoints trained from one start."""
    from trivla_drake.train.export_job import SoupConfig

    def run(config: SoupConfig) -> int:
        from trivla_drake.train.export_job import run_soup as soup

        return _report_model_folder(soup(config), f": the average of {len(config.checkpoints)} models", config.dtype)

    return _run_job("soup", args, lambda args: with_flags(
        config_from_args(SoupConfig, args), {"checkpoints": list(args.checkpoints), **_job_flags(args)}), run)


def add_soup_parser(commands) -> argparse.ArgumentParser:
    """Register `soup` on an argparse subparsers object."""
    parser = _add_job_parser(
        commands, "soup", run_soup, "SoupConfig (trivla_drake/train/export_job.py)", "dtype, drop_unused_llm_layers",
        help="average the weights of policy checkpoints trained from one start (e.g. follow runs that differ in "
             "their seed) into one model, written as export writes one")
    parser.add_argument("checkpoints", nargs="+", metavar="CHECKPOINT",
                        help="two or more checkpoint folders with the same config.json and the same frozen "
                             "Systems 2 and 3 (runs' final/)")
    add_out_arguments(parser)
    return parser


def run_refit_command(args: argparse.Namespace) -> int:
    """`trivla-drake refit`: re-fits a checkpoint's instruction-grounding read-out (train/refit_job.py)."""
    from trivla_drake.train.refit_job import RefitConfig

    def run(config: RefitConfig) -> int:
        from trivla_drake.train.refit_job import report_path, run_refit

        report = run_refit(config, progress=not args.no_progress)
        print(json.dumps({"out": config.out, "report": report_path(config),
                          "median_and_p90_xy_error_cm": report["median_and_p90_xy_error_cm"]}))
        return 0

    return _run_job("refit", args, lambda args: with_flags(
        config_from_args(RefitConfig, args), {"checkpoint": args.checkpoint, "data": args.data, **_job_flags(args)}),
        run)


def add_refit_parser(commands) -> argparse.ArgumentParser:
    """Register `refit` on an argparse subparsers object."""
    parser = _add_job_parser(
        commands, "refit", run_refit_command, "RefitConfig (trivla_drake/train/refit_job.py)",
        "scenes, steps, lr, threads, ...",
        help="re-fit a checkpoint's instruction-grounding read-out on rendered scenes and a dataset's frames (the "
             "shipped recipe's last training stage)")
    parser.add_argument("checkpoint", help="the model folder whose grounding read-out is re-fitted")
    parser.add_argument("--data", default=None, help="the LeRobot dataset it was trained on")
    add_out_arguments(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress output")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Standalone entry point with just `train` (also what torchrun runs with -m)."""
    parser = argparse.ArgumentParser(prog="trivla-drake")
    commands = parser.add_subparsers(dest="command", required=True)
    add_train_parser(commands)
    args = parser.parse_args(argv)
    return args.run(args)


if __name__ == "__main__":
    sys.exit(main())
