"""The `train` subcommand, for `trivla_drake.cli` to register:

    from trivla_drake.train.cli_commands import add_train_parser
    add_train_parser(commands)      # commands = parser.add_subparsers(...)

    trivla-drake train --stage video  --data DEMOS --out runs/video
    trivla-drake train --stage vlm    --out runs/vlm    --init runs/video/final
    trivla-drake train --stage policy --data DEMOS --out runs/policy --init runs/vlm/final
    torchrun --nproc_per_node 2 -m trivla_drake.train.cli_commands train --stage policy ...

`run_train(args)` returns the exit code (user errors print one line and return 2).
`python -m trivla_drake.train.cli_commands train ...` runs it without cli.py (and under torchrun).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from trivla_drake.train.config import GROUNDING_PHASES, TrainConfig

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: no spinning OpenMP threads on shared cores


def _user_errors():
    from trivla_drake.data.lerobot import NotADatasetError

    return (ValueError, NotADatasetError, FileNotFoundError, FloatingPointError)


def config_from_args(args: argparse.Namespace):
    """The TrainConfig the command line asks for."""

    return TrainConfig(
        stage=args.stage,
        out=args.out,
        data=args.data,
        extra_data=tuple(args.extra_data or ()),
        preset=args.preset,
        init=args.init,
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        warmup_steps=args.warmup_steps,
        min_lr_ratio=args.min_lr_ratio,
        beta2=args.beta2,
        grad_clip=args.grad_clip,
        ema_decay=args.ema_decay,
        checkpoint_every=args.checkpoint_every,
        resume=args.resume,
        seed=args.seed,
        workers=args.workers,
        use_system2=not args.no_system2,
        use_system3=not args.no_system3,
        cache_dir=args.cache_dir,
        feature_stride=args.feature_stride,
        feature_dtype=args.feature_dtype,
        vl_position_embedding=args.vl_position_embedding,
        dense_weight=args.dense_weight,
        dense_subcells=args.dense_subcells,
        grounding_weight=args.grounding_weight,
        grounding_lr_scale=args.grounding_lr_scale,
        grounding_phase=args.grounding_phase,
        subgoal_offset=args.subgoal_offset,
        keep_grounding=args.keep_grounding,
        grounding_carry_tasks=tuple(t for t in (args.grounding_carry_tasks or "").split(",") if t),
        system2_from=args.system2_from,
        fresh_system1=args.fresh_system1,
        grounding_reads_gripper=args.grounding_reads_gripper,
        bind_held_only=args.bind_held_only,
        clip_seconds=args.clip_seconds,
        future_stride=args.future_stride,
        keep_checkpoints=args.keep_checkpoints,
        threads=args.threads,
        precision=args.precision,
        progress=not args.no_progress,
    )


def run_train(args: argparse.Namespace) -> int:
    """`trivla-drake train`: one training stage; prints the summary."""
    from trivla_drake.train.trainer import train

    try:
        summary = train(config_from_args(args))
    except _user_errors() as error:
        print(f"trivla-drake train: error: {error}", file=sys.stderr)
        return 2
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


def add_train_parser(commands) -> argparse.ArgumentParser:
    """Register `train` on an argparse subparsers object."""
    parser = commands.add_parser(
        "train", help="train one TriVLA stage: video (System 3), vlm (System 2) or policy (System 1)",
        description="Train one stage. Run video, then vlm with --init VIDEO_OUT/final, then policy with "
                    "--init VLM_OUT/final. Under torchrun every process trains (DDP); rank 0 writes.",
    )
    parser.add_argument("--stage", required=True, choices=("video", "vlm", "policy"), help="what to train")
    parser.add_argument("--data", default=None,
                        help="LeRobot dataset folder (video, policy); for vlm an optional folder for the "
                             "generated visual-question set")
    parser.add_argument("--extra-data", action="append", default=None, metavar="FOLDER",
                        help="policy stage: another LeRobot dataset folder to train on with --data (repeatable; "
                             "normalisation over all of them, an episode two folders both hold is trained on once)")
    parser.add_argument("--out", required=True, help="run folder: checkpoints/, final/, log.jsonl, summary.json")
    parser.add_argument("--preset", default=None, help="model preset: tiny, cpu, paper (default: --init's, else cpu)")
    parser.add_argument("--init", default=None, metavar="CHECKPOINT_DIR",
                        help="start from this checkpoint (the previous stage's final/); default: a fresh preset")
    parser.add_argument("--steps", type=int, default=None, help="optimizer steps (default per stage: 3000/3000/10000)")
    parser.add_argument("--batch-size", type=int, default=None,
                        help="samples per process per step (default per stage: video 8, vlm 8, policy 32)")
    parser.add_argument("--lr", type=float, default=None, help="peak learning rate (default: video 1e-4, vlm 3e-4, "
                        "policy 1e-4)")
    parser.add_argument("--warmup-steps", type=int, default=TrainConfig.warmup_steps,
                        help=f"linear warm-up steps (at most a tenth of the run; default {TrainConfig.warmup_steps})")
    parser.add_argument("--min-lr-ratio", type=float, default=TrainConfig.min_lr_ratio,
                        help="after warm-up the rate follows a cosine down to lr x this at the last step; 1 keeps it "
                             f"constant (default {TrainConfig.min_lr_ratio})")
    parser.add_argument("--beta2", type=float, default=TrainConfig.beta2, help=f"AdamW beta2 (default {TrainConfig.beta2})")
    parser.add_argument("--grad-clip", type=float, default=TrainConfig.grad_clip,
                        help=f"clip the gradient norm to this; 0: no clipping (default {TrainConfig.grad_clip})")
    parser.add_argument("--ema-decay", type=float, default=TrainConfig.ema_decay,
                        help="checkpoints hold a moving average of the trained weights over about the last "
                             "1/(1 - D) steps (0.999: 1000), as diffusion policies are usually evaluated; the "
                             "trained weights stay in the training state; 0: the last "
                             f"step's weights (default {TrainConfig.ema_decay:g})")
    parser.add_argument("--checkpoint-every", type=int, default=500, help="steps between checkpoints (default 500)")
    parser.add_argument("--resume", action="store_true", help="continue from the newest checkpoint in --out")
    parser.add_argument("--seed", type=int, default=0, help="seed of initialisation, data order and noise")
    parser.add_argument("--workers", type=int, default=0, help="DataLoader workers per process (default 0)")
    parser.add_argument("--no-system2", action="store_true", help="ablation: a model without System 2")
    parser.add_argument("--no-system3", action="store_true", help="ablation: a model without System 3")
    parser.add_argument("--cache-dir", default=None,
                        help="folder for decoded clips, the VQA set and System 2/3 features "
                             "(default ~/.cache/trivla_drake/train)")
    parser.add_argument("--feature-stride", type=int, default=1,
                        help="policy: cache and train on every N-th frame (default 1: all)")
    parser.add_argument("--feature-dtype", default="float16", choices=("float16", "bfloat16", "float32"),
                        help="policy: dtype of cached features (default float16)")
    parser.add_argument("--clip-seconds", type=float, default=1.0,
                        help="video: a clip (current + future frames) spans about this long (default 1 s)")
    parser.add_argument("--future-stride", type=int, default=None,
                        help="video: frames between clip frames (default: from --clip-seconds and the fps)")
    parser.add_argument("--keep-checkpoints", type=int, default=2, help="periodic checkpoints kept (default 2)")
    parser.add_argument("--dense-weight", type=float, default=0.0,
                        help="vlm: weight of a dense loss that trains System 2's image tokens to say which blocks "
                             "their image cells show (from the renderer's label images); 0: none")
    parser.add_argument("--dense-subcells", type=int, default=None,
                        help="vlm, with --dense-weight: split each image token's cell into N x N sub-cells "
                             "whose blocks the dense loss asks for, so the tokens say where in their cell a "
                             "block lies (default: as --init's head has them; 1, the whole cell, for a new head)")
    parser.add_argument("--vl-position-embedding", action="store_true",
                        help="policy: give System 1 a learned embedding of System 2's token positions, so it "
                             "knows where in the image a token it reads lies (added when --init has none)")
    parser.add_argument("--grounding-weight", type=float, default=0.0,
                        help="policy: give System 1 an instruction grounding (the instruction's tokens query System "
                             "2's image tokens for the next gripper event's position, an auxiliary loss of this "
                             "weight; added when --init has none); 0: none")
    parser.add_argument("--grounding-lr-scale", type=float, default=3.0,
                        help="policy: the instruction grounding's learning rate as a multiple of --lr (default 3)")
    parser.add_argument("--grounding-phase", default="joint", choices=GROUNDING_PHASES,
                        help="policy, with --grounding-weight: joint (default) trains System 1 and its grounding "
                             "together; bind trains only the grounding and the Q_vl projection, on the sub-goal "
                             "loss over the approach frames; follow keeps those as --init has them and trains the "
                             "rest of System 1. The two-step recipe is bind, then follow from its checkpoint")
    parser.add_argument("--grounding-carry", dest="grounding_carry_tasks", default=None, metavar="TASKS",
                        help="policy, with --grounding-weight: these tasks' episodes (comma-separated, e.g. "
                             "stack_block) also train the grounding on the frames that carry the held block to its "
                             "release, labelled with the release position: the frames that ask for the "
                             "destination's colour (default: the approach frames alone)")
    parser.add_argument("--keep-grounding", action="store_true",
                        help="policy, --grounding-phase bind with --init: go on binding the --init checkpoint's "
                             "grounding instead of a fresh one (bind on few scenes first, then on more)")
    parser.add_argument("--system2-from", default=None, metavar="CHECKPOINT",
                        help="policy, with --init: replace --init's System 2 by this checkpoint's (e.g. one "
                             "retrained with --stage vlm), keeping System 1 and 3; its features are cached anew "
                             "(System 3's copied from the cache of --init's model)")
    parser.add_argument("--fresh-system1", action="store_true",
                        help="policy, with --init: train a fresh System 1 (drawn from --seed) on --init's Systems 2 "
                             "and 3, keeping its System 1 options (e.g. the 10%%-data arm of the tables); with "
                             "--grounding-phase follow it keeps --init's instruction grounding")
    parser.add_argument("--grounding-reads-gripper", action="store_true",
                        help="policy, with --grounding-weight: the instruction grounding also reads how far the "
                             "gripper is closed and answers with a second read-out while a block is held, so an "
                             "instruction can name one block before the grasp and another after it (use with "
                             "--grounding-carry; added as a copy of the read-out when --init's grounding has none)")
    parser.add_argument("--bind-held-only", action="store_true",
                        help="bind, with --keep-grounding --grounding-reads-gripper: train only the held-block "
                             "read-out, so the answers with no block held stay --init's exactly")
    parser.add_argument("--subgoal-offset", action="store_true",
                        help="policy, with --grounding-weight: also give System 1's state token the grounding's "
                             "sub-goal relative to the tool-centre point (added, starting at zero, when --init "
                             "has none)")
    parser.add_argument("--threads", type=int, default=None, help="torch threads per process (default: torch's)")
    parser.add_argument("--precision", default="fp32", choices=("fp32", "bf16"), help="bf16 autocast on CUDA")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    parser.set_defaults(run=run_train)
    return parser


def holds_model_export(folder) -> bool:
    """Whether `folder` holds just what `export` and `soup` write: a checkpoint's config.json and weights (and its
    tokenizer folders), nothing else."""
    from pathlib import Path

    from trivla_drake.nn.checkpoint import CONFIG_FILE, WEIGHTS_FILE, read_checkpoint_config

    names = {p.name for p in Path(folder).iterdir() if not (p.is_dir() and p.name.startswith("tokenizer_"))}
    if names != {CONFIG_FILE, WEIGHTS_FILE}:
        return False
    try:
        read_checkpoint_config(str(folder))
    except ValueError:
        return False
    return True


def _write_model_folder(command: str, args: argparse.Namespace, write, what: str = "") -> int:
    """Runs `write()` (-> the folder written) and reports the folder's size, or a user error as exit code 2. First
    `--out` is checked (before any model loads): a folder other than an earlier export is replaced only with
    --overwrite, and never the working folder."""
    from trivla_drake.train.atomic_folder import check_replaceable_folder

    try:
        check_replaceable_folder(args.out, flag="--out", holds_earlier_output=holds_model_export,
                                 what="model (config.json and model.safetensors)", overwrite=args.overwrite)
        target = write()
    except _user_errors() as error:
        print(f"trivla-drake {command}: error: {error}", file=sys.stderr)
        return 2
    size = sum(p.stat().st_size for p in target.rglob("*") if p.is_file())
    print(f"wrote {target}{what} ({size / 1e6:.1f} MB, weights in {args.dtype})")
    return 0


def add_out_arguments(parser: argparse.ArgumentParser) -> None:
    """--out and --overwrite of `export` and `soup`."""
    parser.add_argument("--out", required=True,
                        help="folder to write; an earlier export there is replaced atomically once the new one is "
                             "complete, any other non-empty folder only with --overwrite")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace --out even when it holds other things than an earlier export (they are deleted; "
                             "never the working folder)")


def run_export(args: argparse.Namespace) -> int:
    """`trivla-drake export`: a checkpoint's model, without optimizer state, in a smaller dtype."""
    from trivla_drake.train.checkpoints import export_checkpoint

    return _write_model_folder("export", args, lambda: export_checkpoint(
        args.checkpoint, args.out, weights_dtype=args.dtype, drop_unused_llm_layers=args.drop_unused_llm_layers))


def add_export_parser(commands) -> argparse.ArgumentParser:
    """Register `export` on an argparse subparsers object."""
    parser = commands.add_parser(
        "export", help="write a checkpoint's model (no optimizer state) with float16 weights, e.g. for "
                       "models/trivla_cpu")
    parser.add_argument("checkpoint", help="checkpoint folder (a run's final/ or checkpoints/step-N/)")
    add_out_arguments(parser)
    parser.add_argument("--dtype", default="float16", choices=("float16", "bfloat16", "float32"),
                        help="stored weight type (default float16); loading casts back to float32")
    parser.add_argument("--drop-unused-llm-layers", action="store_true",
                        help="keep only System 2's LLM layers up to its read-out layer (select_layer): the "
                             "same actions from a smaller file, but no longer a start for --stage vlm")
    parser.set_defaults(run=run_export)
    return parser


def run_soup(args: argparse.Namespace) -> int:
    """`trivla-drake soup`: the uniform weight average of checkpoints trained from one start."""
    from trivla_drake.train.model_soup import soup_checkpoints

    return _write_model_folder("soup", args, lambda: soup_checkpoints(
        args.checkpoints, args.out, weights_dtype=args.dtype, drop_unused_llm_layers=args.drop_unused_llm_layers),
        f": the average of {len(args.checkpoints)} models")


def add_soup_parser(commands) -> argparse.ArgumentParser:
    """Register `soup` on an argparse subparsers object."""
    parser = commands.add_parser(
        "soup", help="average the weights of policy checkpoints trained from one start (e.g. follow runs that "
                     "differ in their seed) into one model, written as export writes one")
    parser.add_argument("checkpoints", nargs="+", metavar="CHECKPOINT",
                        help="two or more checkpoint folders with the same config.json and the same frozen "
                             "Systems 2 and 3 (runs' final/)")
    add_out_arguments(parser)
    parser.add_argument("--dtype", default="float16", choices=("float16", "bfloat16", "float32"),
                        help="stored weight type (default float16); the average is taken in float32")
    parser.add_argument("--drop-unused-llm-layers", action="store_true",
                        help="keep only System 2's LLM layers up to its read-out layer, as export does")
    parser.set_defaults(run=run_soup)
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
