"""Re-fitting the instruction grounding's read-out on rendered scenes (the job: train/refit_job.py).

The grounding (nn/instruction_grounding.py) reads Q_vl through the Q_vl path that System 1's DiT also
reads (vl_norm, vl_proj, vl_position), and gives System 1 its sub-goal. `refit_readout` trains only the
grounding's read-out (`readout_parameters`: the grounding but its goal projection) on Q_vl computed once
from two sources, mixed in every batch: rendered grounding scenes (train/grounding_scenes.py: many
layouts) and a dataset's grounding frames (data/samples.py: what a bind run trains on, so the frames
along real approaches and while carrying stay fitted). Everything else System 1 reads stays as it was
(the feature statistics too), so no follow run is needed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from trivla_drake.nn.panda_tcp import denormalize_position

GROUNDING_CARRY_TASKS = ("stack_block", "place_in_bowl", "unstack_block", "rotate_block_left", "rotate_block_right")


@dataclass
class GroundingSamples:
    """Precomputed grounding inputs and labels: Q_vl float16 (N, S, D) right-padded with its mask (N, S),
    states (N, 18), sub-goal positions (N, 3) [m], and each sample's task (the yaw labels went with the
    experiments: the read-out's loss is on the position)."""

    q_vl: torch.Tensor
    q_vl_mask: torch.Tensor
    state: torch.Tensor
    subgoal_position: torch.Tensor
    tasks: list[str]

    def __len__(self) -> int:
        return len(self.tasks)

    def batch(self, rows: torch.Tensor, length: int) -> dict[str, torch.Tensor]:
        """`compute_grounding_loss`'s batch of `rows`, Q_vl padded to `length` tokens."""
        pad = length - self.q_vl.shape[1]
        return {
            "q_vl": torch.nn.functional.pad(self.q_vl[rows].float(), (0, 0, 0, pad)),
            "q_vl_mask": torch.nn.functional.pad(self.q_vl_mask[rows], (0, pad)),
            "state": self.state[rows], "subgoal_position": self.subgoal_position[rows],
        }


def _padded(sequences: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    longest = max(len(s) for s in sequences)
    q_vl = torch.zeros(len(sequences), longest, sequences[0].shape[1], dtype=torch.float16)
    mask = torch.zeros(len(sequences), longest, dtype=torch.bool)
    for i, s in enumerate(sequences):
        q_vl[i, : len(s)], mask[i, : len(s)] = s, True
    return q_vl, mask


@torch.inference_mode()
def _encode(model, static: np.ndarray, wrist: np.ndarray, instructions: list[str], batch_size: int) -> list[torch.Tensor]:
    """System 2's Q_vl (valid tokens only, float16) of uint8 views (N, S, S, 3) at the model's image size."""
    out = []
    for start in range(0, len(instructions), batch_size):
        q, mask = model.encode_vision_language_batch(
            torch.from_numpy(np.array(static[start : start + batch_size])),  # a writable copy of a memory-mapped block
            torch.from_numpy(np.array(wrist[start : start + batch_size])),
            instructions[start : start + batch_size])
        out += [q[i, mask[i]].to(torch.float16).clone() for i in range(len(q))]
    return out


def scene_samples(model, scenes, *, batch_size: int = 32, progress: bool = True) -> GroundingSamples:
    """Q_vl of every rendered grounding scene (train/grounding_scenes.GroundingScenes) with its labels."""
    from tqdm import tqdm

    if scenes.static.shape[1] != model.image_size:
        raise ValueError(f"the grounding scenes in {scenes.folder} are {scenes.static.shape[1]} px; the model reads "
                         f"{model.image_size} px: render them at its image size")
    sequences = []
    step = 512
    for start in tqdm(range(0, len(scenes.instructions), step), desc="System 2 on grounding scenes", unit="block", disable=not progress):
        sl = slice(start, start + step)
        sequences += _encode(model, scenes.static[sl], scenes.wrist[sl], scenes.instructions[sl], batch_size)
    q_vl, mask = _padded(sequences)
    return GroundingSamples(q_vl, mask, torch.from_numpy(scenes.state.copy()),
                            torch.from_numpy(scenes.subgoal_position.copy()),
                            list(scenes.tasks))


def dataset_samples(model, reader, *, stride: int, static_camera: str, wrist_camera: str,
                    carry_tasks: tuple[str, ...] = GROUNDING_CARRY_TASKS, batch_size: int = 32,
                    progress: bool = True) -> GroundingSamples:
    """Q_vl of every `stride`-th grounding frame of a dataset (before each episode's first gripper change,
    and the carrying frames of `carry_tasks`; TrainingSamples.grounding_frames) with its labels."""
    from tqdm import tqdm

    from trivla_drake.data.samples import TrainingSamples
    from trivla_drake.train.datasets import STATE_KEY, check_cameras, resize_frames

    if stride < 1:
        raise ValueError(f"stride must be >= 1; got {stride}")
    check_cameras(reader, [static_camera, wrist_camera])
    samples = TrainingSamples(reader, history=1, future_frames=0, cameras=[], cache_episodes=1,
                              grounding_carry_tasks=tuple(carry_tasks))
    starts = np.concatenate([[0], np.cumsum([int(e["length"]) for e in reader.episodes])])
    sequences, states, positions, tasks = [], [], [], []
    for episode in tqdm(range(reader.num_episodes), desc="System 2 on grounding frames", unit="episode",
                        disable=not progress):
        frames = np.flatnonzero(samples.grounding_frames(episode))[::stride]
        if not len(frames):
            continue
        labelled = [samples[int(starts[episode] + t)] for t in frames]
        static = resize_frames(reader.episode_video(episode, static_camera)[frames], model.image_size)
        wrist = resize_frames(reader.episode_video(episode, wrist_camera)[frames], model.image_size)
        sequences += _encode(model, static, wrist, [reader.task_of(episode)] * len(frames), batch_size)
        states.append(np.stack([np.asarray(x[STATE_KEY][-1], dtype=np.float32) for x in labelled]))
        positions.append(np.stack([x["subgoal_position"] for x in labelled]))
        tasks += [str(reader.episodes[episode].get("trivla/task") or reader.task_of(episode))] * len(frames)
    if not sequences:
        raise ValueError(f"the dataset at {reader.root} has no grounding frames (none before a gripper change)")
    q_vl, mask = _padded(sequences)
    return GroundingSamples(q_vl, mask, torch.from_numpy(np.concatenate(states)),
                            torch.from_numpy(np.concatenate(positions).astype(np.float32)),
                            tasks)


def readout_parameters(model) -> dict[str, torch.nn.Parameter]:
    """The grounding's read-out by name: its parameters but the goal projection System 1 reads."""
    return {name: p for name, p in model.policy.binding_parameters().items() if name.startswith("grounding.")}


@torch.no_grad()
def grounding_outputs(model, samples: GroundingSamples, *, batch_size: int = 128) -> tuple[torch.Tensor, torch.Tensor]:
    """The grounding's goal token (N, D) and raw sub-goal (N, 3) or (N, 5) of every sample
    (TriVLA.grounding_of_features), in eval mode."""
    model.eval()
    goals, subgoals = [], []
    for start in range(0, len(samples), batch_size):
        b = samples.batch(torch.arange(start, min(start + batch_size, len(samples))), samples.q_vl.shape[1])
        goal, subgoal = model.grounding_of_features(b["q_vl"], b["q_vl_mask"], b["state"])
        goals.append(goal.float())
        subgoals.append(subgoal.float())
    return torch.cat(goals), torch.cat(subgoals)


def raw_subgoals(model, samples: GroundingSamples, *, batch_size: int = 128) -> torch.Tensor:
    """The grounding's raw sub-goal of every sample (N, 3) or (N, 5) (TriVLA.subgoal_of_features), in eval mode."""
    return grounding_outputs(model, samples, batch_size=batch_size)[1]


def offsets_from_raw(raw: torch.Tensor, samples: GroundingSamples) -> np.ndarray:
    """Raw sub-goals (N, 3) or (N, 5) of `samples` (`grounding_outputs`) minus each sample's label [m], (N, 3)."""
    return (denormalize_position(raw[:, :3]) - samples.subgoal_position).numpy()


def subgoal_offsets(model, samples: GroundingSamples, *, batch_size: int = 128) -> np.ndarray:
    """The grounding's sub-goal minus each sample's label [m], (N, 3)."""
    return offsets_from_raw(raw_subgoals(model, samples, batch_size=batch_size), samples)


def subgoal_errors(model, samples: GroundingSamples, *, batch_size: int = 128) -> np.ndarray:
    """x-y distance [m] (N,) of the grounding's sub-goal from each sample's label."""
    return np.linalg.norm(subgoal_offsets(model, samples, batch_size=batch_size)[:, :2], axis=1)


def refit_readout(model, scenes: GroundingSamples, frames: GroundingSamples, *, steps: int, lr: float,
                  scene_share: float = 0.5, batch_size: int = 64, seed: int = 0, log_every: int = 100,
                  progress: bool = True) -> list[tuple[int, float]]:
    """Adam on the grounding's read-out alone (`readout_parameters`), each batch `scene_share` rendered
    scenes and the rest dataset frames, drawn with replacement. Returns the loss EMA every `log_every` steps."""
    from tqdm import tqdm

    from trivla_drake.nn.instruction_grounding import grounding_loss

    if steps < 1 or not lr > 0 or batch_size < 2:
        raise ValueError(f"steps must be >= 1, lr > 0 and batch_size >= 2; got {steps}, {lr}, {batch_size}")
    if not 0.0 < scene_share < 1.0:
        raise ValueError(f"scene_share must be in (0, 1); got {scene_share}")
    trained = readout_parameters(model)
    for name, p in model.named_parameters():
        p.requires_grad_(False)
    params = [p for name, p in model.policy.named_parameters() if name in trained]
    for p in params:
        p.requires_grad_(True)
    optimizer = torch.optim.Adam(params, lr=lr)
    generator = torch.Generator().manual_seed(seed)
    from_scenes = int(round(batch_size * scene_share))
    length = max(scenes.q_vl.shape[1], frames.q_vl.shape[1])
    ema, curve = None, []
    bar = tqdm(range(steps), desc="re-fitting the grounding", unit="step", disable=not progress)
    for step in bar:
        model.policy.grounding.train()
        scene_rows = torch.randint(len(scenes), (from_scenes,), generator=generator)
        frame_rows = torch.randint(len(frames), (batch_size - from_scenes,), generator=generator)
        parts = [scenes.batch(scene_rows, length), frames.batch(frame_rows, length)]
        batch = {key: torch.cat([p[key] for p in parts]) for key in parts[0]}
        _, now = model.grounding_of_features(batch["q_vl"], batch["q_vl_mask"], batch["state"])
        loss = grounding_loss(now, batch["subgoal_position"], None)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        value = float(loss.detach())
        ema = value if ema is None else 0.98 * ema + 0.02 * value
        if (step + 1) % log_every == 0 or step + 1 == steps:
            curve.append((step + 1, ema))
            bar.set_postfix(loss=f"{ema:.4f}")
    model.requires_grad_(False)
    model.eval()
    return curve


def save_samples(samples: GroundingSamples, path) -> None:
    """Writes `samples` to `path` (a .pt file) atomically: a crash leaves the old file or none, never half of one."""
    import os
    from pathlib import Path

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    torch.save({"format": 1, "q_vl": samples.q_vl, "q_vl_mask": samples.q_vl_mask, "state": samples.state,
                "subgoal_position": samples.subgoal_position,
                "tasks": list(samples.tasks)}, tmp)
    os.replace(tmp, path)


def load_samples(path) -> GroundingSamples:
    """The samples `save_samples` wrote to `path`; ValueError naming the file when it is not such a file."""
    try:
        saved = torch.load(path, weights_only=True)
    except Exception as error:  # a truncated or foreign file
        raise ValueError(f"{path} holds no saved grounding samples ({type(error).__name__}: {error}); delete it "
                         "and it is computed again") from error
    if not isinstance(saved, dict) or saved.get("format") != 1:
        raise ValueError(f"{path} holds no saved grounding samples of format 1; delete it and it is computed again")
    return GroundingSamples(saved["q_vl"], saved["q_vl_mask"], saved["state"], saved["subgoal_position"],
                            list(saved["tasks"]))  # (a file of before also holds yaw labels: unused)
