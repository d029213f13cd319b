"""`train(config)`: one training stage (video, vlm or policy), in one process or under torchrun: the training loop.

    from trivla_drake.train import TrainConfig, train
    summary = train(TrainConfig(stage="policy", data="data/demos", out="runs/policy", init="runs/vlm/final"))

What happens, in order: the output folder is checked (an existing run needs `resume`, and its saved config must
match); the model is built (model_setup.py: resumed checkpoint > `init` checkpoint > fresh preset) and checked
against the dataset before anything is computed; the stage's data is prepared once and cached (stage_data.py:
decoded clips, the generated VQA set, System 2/3 features); then AdamW steps with warm-up + cosine learning rate
(optimization.py), a checkpoint every `checkpoint_every` steps and at the end (OUT/final, loadable by
`trivla_drake.nn.load_checkpoint`). OUT/train_config.yaml holds the run's full config.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from torch import nn

from trivla_drake.config_io import save_config
from trivla_drake.data.durable import atomic_write_text
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.train import checkpoints as ckpt
from trivla_drake.train.config import TrainConfig, check_resume_compatible
from trivla_drake.train.distributed import DistEnv, setup_distributed, teardown_distributed
from trivla_drake.train.features import hash_module_weights
from trivla_drake.train.model_setup import build_model, resolve_preset, trainable_module
from trivla_drake.train.optimization import learning_rate, make_optimizer
from trivla_drake.train.rng_state import rank_seed, rng_state, set_rng_state
from trivla_drake.train.stage_data import fit_policy_normalization, prepare_data
from trivla_drake.train.weight_average import WeightAverage

StepCallback = Callable[[int], None]


class StageLoss(nn.Module):
    """The stage's loss as a module's forward (what DistributedDataParallel wraps)."""

    def __init__(self, model: TriVLA, stage: str, generator: torch.Generator, dense_weight: float = 0.0,
                 grounding_weight: float = 0.0, grounding_phase: str = "joint") -> None:
        super().__init__()
        self.model, self.stage, self.generator = model, stage, generator
        self.dense_weight = dense_weight
        self.grounding_weight, self.grounding_phase = grounding_weight, grounding_phase

    def forward(self, batch: dict[str, Any]) -> tuple[torch.Tensor, dict[str, float]]:
        if self.stage == "video":
            return self.model.compute_video_loss(batch, generator=self.generator)
        if self.stage == "vlm":
            return self.model.compute_vlm_loss(batch, dense_weight=self.dense_weight)
        if self.grounding_phase == "bind":
            return self.model.compute_grounding_loss(batch)
        return self.model.compute_loss(batch, generator=self.generator, grounding_weight=self.grounding_weight)


def weights_digest(model: nn.Module) -> str:
    """sha256 of every weight and buffer of `model` (equal digests = bit-identical weights)."""
    hasher = hashlib.sha256()
    hash_module_weights(model, hasher)
    return hasher.hexdigest()


def _note(env: DistEnv, message: str) -> None:
    """A one-line notice on stderr, from rank 0 only."""
    if env.is_main:
        print(f"trivla-drake train: note: {message}", file=sys.stderr)


def _truncate_log(path: Path, last_step: int) -> None:
    """Keeps the log lines of steps <= last_step (all of them gone for a fresh run)."""
    if not path.is_file():
        return
    kept = []
    for line in path.read_text().splitlines():
        try:
            if json.loads(line)["step"] <= last_step:
                kept.append(line)
        except (ValueError, KeyError, TypeError):
            continue
    atomic_write_text(path, "".join(line + "\n" for line in kept))  # a crash here keeps the old log




def train(config: TrainConfig, *, step_callback: StepCallback | None = None) -> dict[str, Any]:
    """Runs one stage (see the module doc); returns a summary (also written to OUT/summary.json).
    `step_callback(step)` is called after every step, once its checkpoint (if any) is written."""
    config = config.resolved()
    env = setup_distributed(config.dist_timeout_minutes)
    try:
        return _train(config, env, step_callback)
    finally:
        teardown_distributed(env)


def _train(config: TrainConfig, env: DistEnv, step_callback: StepCallback | None) -> dict[str, Any]:
    from tqdm import tqdm

    if config.threads is not None:
        torch.set_num_threads(config.threads)
    out = Path(config.out)
    latest = ckpt.latest_checkpoint(out)
    resume_from = None
    if latest is not None and not config.resume:
        raise ValueError(f"{out} already holds a training run (newest checkpoint: {latest}); "
                         "pass --resume to continue it, or choose another --out")
    if config.resume and latest is not None:
        latest, skipped = ckpt.newest_intact_checkpoint(out, set_aside=env.is_main)
        if latest is None:
            raise ValueError(f"cannot resume {out}: no checkpoint of it is intact ("
                             + "; ".join(f"{path}: {why}" for path, why, _ in skipped)
                             + "); start a new run with another --out")
        for path, why, kept in skipped:
            _note(env, f"warning: skipping checkpoint {path} ({why}); resuming from the newest intact one, {latest} "
                       f"(the broken one is kept, as {kept})")
        saved = ckpt.load_train_config(latest)
        if config.preset is None:
            config = dataclasses.replace(config, preset=saved.preset)
        check_resume_compatible(saved, config)
        resume_from = latest
    else:
        if config.resume:
            _note(env, f"nothing to resume in {out}; starting a new run")
        config = dataclasses.replace(config, preset=resolve_preset(config))
        if config.stage == "policy" and not config.init and (config.use_system2 or config.use_system3):
            _note(env, "the policy stage starts from a fresh preset: Systems 2 and 3 are untrained "
                       "(pass --init with the vlm stage's final checkpoint)")
    config.validate()

    reader, readers = None, []
    if config.stage in ("video", "policy"):
        from trivla_drake.data.lerobot_reader import LeRobotReader

        reader = LeRobotReader(config.data)
        readers = [reader, *(LeRobotReader(folder) for folder in config.extra_data)]
    model = build_model(config, resume_from)
    train_state = ckpt.load_train_state(resume_from) if resume_from is not None else None
    if config.stage == "policy":
        fit_policy_normalization(config, model, readers, resume_from, note=lambda message: _note(env, message))

    torch.manual_seed(config.seed)
    model.requires_grad_(False)
    trained = trainable_module(model, config.stage)
    trained.requires_grad_(True)
    if config.stage == "policy" and config.policy.grounding.phase != "joint":
        binding = model.policy.binding_parameters()  # bind trains only these; follow all but these
        trained_in_bind = model.policy.held_parameters() if config.policy.grounding.bind_held_only else binding
        for name, p in model.policy.named_parameters():
            p.requires_grad_(name in trained_in_bind if config.policy.grounding.phase == "bind" else name not in binding)
    if config.stage == "vlm" and model.vision_language.block_head is not None and not config.vlm.dense_weight:
        model.vision_language.block_head.requires_grad_(False)  # no dense loss: the head gets no gradient
    model.to(env.device)
    model.eval()
    trained.train()

    prepare_started = time.time()
    for one in readers:  # a corrupted or replaced data / video file stops the run before any caching, naming it
        one.verify_files()
    dataset, collate, data_summary = prepare_data(config, model, readers, env)
    # A resumed run keeps its checkpoint's statistics, a follow run its bind run's (what the binding learnt on),
    # and a held-only bind its --init's (everything but the held-block read-out stays as it was).
    if (config.stage == "policy" and train_state is None and config.policy.grounding.phase != "follow"
            and not config.policy.grounding.bind_held_only):
        from trivla_drake.train.feature_statistics import fit_feature_standardizers

        data_summary.update(fit_feature_standardizers(model, dataset.shards, progress=config.progress and env.is_main))
    data_summary["data_prepare_s"] = time.time() - prepare_started
    start_step = int(train_state["step"]) if train_state else 0
    if train_state and train_state.get("world_size") != env.world_size:
        _note(env, f"resuming a run of {train_state.get('world_size')} processes with {env.world_size}; "
                   "the data order from here differs from an uninterrupted run")

    from trivla_drake.train.sampler import StepBatchSampler

    sampler = StepBatchSampler(len(dataset), config.batch_size, seed=config.seed, rank=env.rank,
                               world_size=env.world_size, start_step=start_step, total_steps=config.steps)
    loader = torch.utils.data.DataLoader(dataset, batch_sampler=sampler, collate_fn=collate,
                                         num_workers=config.workers, persistent_workers=False)
    optimizer = make_optimizer(trained, config)
    generator = torch.Generator().manual_seed(rank_seed(config.seed, env.rank))
    if train_state is not None:
        optimizer.load_state_dict(train_state["optimizer"])
        rng = train_state["rng"]
        set_rng_state(rng[env.rank] if env.rank < len(rng) else rng[0], generator)
        if env.rank >= len(rng):
            generator.manual_seed(rank_seed(config.seed, env.rank) + start_step)
    average = WeightAverage(model, config.ema_decay) if config.ema_decay > 0 else None
    if average is not None and train_state is not None:
        if "weight_average" not in train_state:
            raise ValueError(f"cannot resume {resume_from}: it holds no weight average")
        average.load_state_dict(train_state["weight_average"])  # and the trained weights back into the model
    loss_module = StageLoss(model, config.stage, generator, config.vlm.dense_weight, config.policy.grounding.weight,
                            config.policy.grounding.phase)
    runner: nn.Module = loss_module
    if env.distributed:
        runner = nn.parallel.DistributedDataParallel(
            loss_module, device_ids=[env.device.index] if env.device.type == "cuda" else None,
            find_unused_parameters=False,  # every trained weight gets a gradient in all three losses
        )
    params = [p for p in trained.parameters() if p.requires_grad]
    autocast = env.device.type == "cuda" and config.precision == "bf16"

    log_path = out / "log.jsonl"
    if env.is_main:
        out.mkdir(parents=True, exist_ok=True)
        save_config(config, out / ckpt.TRAIN_CONFIG_FILE)  # the run's full config (as resumed last)
        _truncate_log(log_path, start_step)  # lines of steps after the resumed checkpoint are redone
    bar = tqdm(total=config.steps, initial=start_step, desc=f"train {config.stage}", unit="step",
               disable=not (config.progress and env.is_main), dynamic_ncols=True)
    loss_ema = train_state.get("loss_ema") if train_state else None
    step = start_step
    step_times: list[float] = []
    started = time.time()

    def weights_for_checkpoints():
        return average.swapped_in() if average is not None else contextlib.nullcontext()

    def save(at_step: int) -> None:
        states = env.all_gather_object(rng_state(generator))
        if env.is_main:
            state = {"step": at_step, "optimizer": optimizer.state_dict(), "rng": states,
                     "world_size": env.world_size, "loss_ema": loss_ema}
            if average is not None:
                state["weight_average"] = average.state_dict()
            with weights_for_checkpoints():  # the model a checkpoint holds: the average, if there is one
                ckpt.write_checkpoint(out / ckpt.CHECKPOINTS_DIR / ckpt.step_dir_name(at_step), model=model,
                                      train_state=state, config=config)
            ckpt.prune_checkpoints(out, config.keep_checkpoints)
        env.barrier()

    try:
        tick = time.time()
        for batch in loader:
            lr = learning_rate(config, step)
            for group in optimizer.param_groups:
                group["lr"] = lr * group.get("lr_scale", 1.0)
            with torch.autocast("cuda", dtype=torch.bfloat16, enabled=autocast):
                loss, info = runner(batch)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if config.optimizer.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(params, config.optimizer.grad_clip)
            optimizer.step()
            if average is not None:
                average.update()
            step += 1
            mean_loss = env.mean(float(loss.detach()))
            if not math.isfinite(mean_loss):
                raise FloatingPointError(f"the loss became {mean_loss} at step {step}; lower lr (--set lr=...)")
            loss_ema = mean_loss if loss_ema is None else 0.98 * loss_ema + 0.02 * mean_loss
            now = time.time()
            step_times.append(now - tick)
            tick = now
            bar.update(1)
            bar.set_postfix(loss=f"{mean_loss:.4f}", ema=f"{loss_ema:.4f}", lr=f"{lr:.2e}")
            if env.is_main and (step % config.log_every == 0 or step == config.steps):
                with open(log_path, "a") as f:
                    f.write(json.dumps({"step": step, "loss": mean_loss, "loss_ema": loss_ema, "lr": lr,
                                        "step_time_s": step_times[-1], **{k: v for k, v in info.items()
                                                                          if k != "loss"}}) + "\n")
            if step % config.checkpoint_every == 0 or step == config.steps:
                save(step)
            if step_callback is not None:
                step_callback(step)
    finally:
        bar.close()

    if ckpt.latest_checkpoint(out) is None or ckpt.read_step(ckpt.latest_checkpoint(out)) < step:
        save(step)  # nothing was saved yet (e.g. a run resumed at its last step)
    summary: dict[str, Any] = {
        "stage": config.stage, "preset": config.preset, "steps": step, "resumed_from_step": start_step,
        "world_size": env.world_size, "batch_size_per_process": config.batch_size,
        "loss_ema": loss_ema, "wall_s": time.time() - started,
        "step_time_s": float(np.median(step_times[1:] or step_times)) if step_times else None,
        **data_summary,
    }
    if config.stage == "vlm" and env.is_main and config.vlm.vqa_eval_questions > 0:
        from trivla_drake.train import vqa

        eval_started = time.time()
        with weights_for_checkpoints():
            summary.update(vqa.evaluate_vqa(model, vqa.VQADataset(data_summary["vqa_folder"], "eval"),
                                            batch_size=config.batch_size, max_questions=config.vlm.vqa_eval_questions))
        summary["vqa_eval_s"] = time.time() - eval_started
    env.barrier()
    summary["weights_sha256_per_rank"] = env.all_gather_object(weights_digest(model))
    if env.is_main:
        newest = ckpt.latest_checkpoint(out)
        if newest != out / ckpt.FINAL_DIR:
            ckpt.copy_checkpoint(newest, out / ckpt.FINAL_DIR)
        summary["final_checkpoint"] = str(out / ckpt.FINAL_DIR)
        if log_path.exists():
            from trivla_drake.train.loss_plot import plot_training_curve

            plot = plot_training_curve(log_path, out / "loss.png", title=f"{config.stage} stage, {out.name}")
            if plot is not None:
                summary["loss_plot"] = str(plot)
        (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    env.barrier()
    return summary
