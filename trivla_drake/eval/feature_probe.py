"""Linear probes of the frozen features System 1 reads: how well each one tells where the blocks are.

For every demonstration the scene is rebuilt from the episode's recorded task and seed (the suite's
`sample_task_instance`, as the harness did when it was collected), which gives the true (x, y) of
each block at the first frame. Each feature set of that first frame is then regressed onto the block
positions with cross-validated ridge regression (kernel form, since features have far more dimensions
than there are episodes), and the held-out R^2 and RMSE are reported. R^2 near 1: the feature holds
the positions linearly; near 0 or below: it holds nothing a linear read-out finds. Raw pixels of the
same frame are the reference. For System 2's image tokens there are also attention read-outs, the way
System 1 reads them, without and with token positions (`attention_probe`). `trivla-drake probe`
prints the table.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from trivla_drake.data.lerobot import LeRobotReader
from trivla_drake.eval.attention_probe import ATTENTION_PROBE_STEPS, attention_probe
from trivla_drake.eval.collect import CAMERAS
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.tasks.scene import BLOCK_COLORS, Layout
from trivla_drake.tasks.suite import get_task, sample_task_instance
from trivla_drake.train.datasets import resize_frames

DEFAULT_RIDGES = (1e-1, 1e0, 1e1, 1e2, 1e3, 1e4, 1e5)
PIXEL_REFERENCE_SIZE = 32  # side of the downsampled frame used as the raw-pixel reference


@dataclass(frozen=True)
class ProbeResult:
    """Held-out fit of one feature set: per-target R^2 and RMSE [m], and the ridge chosen."""

    feature: str
    dims: int
    r2: list[float]
    rmse: list[float]
    ridge: float

    @property
    def mean_r2(self) -> float:
        """R^2 averaged over the targets."""
        return float(np.mean(self.r2))

    def to_dict(self) -> dict:
        """JSON-able form."""
        return {**asdict(self), "mean_r2": self.mean_r2}


def ridge_probe(
    features: np.ndarray,
    targets: np.ndarray,
    *,
    folds: int = 5,
    ridges: tuple[float, ...] = DEFAULT_RIDGES,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, float]:
    """K-fold cross-validated ridge regression of targets (N, K) on features (N, D), features
    standardised on each training fold. Returns held-out R^2 (K,), RMSE (K,) and the ridge (of
    `ridges`) with the best mean R^2."""
    x = np.asarray(features, dtype=np.float64)
    y = np.asarray(targets, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"features must be 2-D (episodes, dims); got shape {x.shape}")
    if y.ndim != 2:
        raise ValueError(f"targets must be 2-D (episodes, outputs); got shape {y.shape}")
    if x.shape[0] != y.shape[0]:
        raise ValueError(f"features has {x.shape[0]} rows but targets has {y.shape[0]}")
    if folds < 2 or x.shape[0] < 2 * folds:
        raise ValueError(f"folds must be >= 2 with at least 2 episodes per fold; got {folds} for {x.shape[0]}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("features and targets must be finite")
    order = np.random.default_rng(seed).permutation(len(x))
    splits = np.array_split(order, folds)
    variance = y.var(0) + 1e-12
    best: tuple[np.ndarray, np.ndarray, float] | None = None
    for ridge in ridges:
        predicted = np.zeros_like(y)
        for held_out in splits:
            train = np.setdiff1d(order, held_out)
            mean, std = x[train].mean(0), x[train].std(0) + 1e-6
            xt, xh = (x[train] - mean) / std, (x[held_out] - mean) / std
            y_mean = y[train].mean(0)
            gram = xt @ xt.T
            alpha = np.linalg.solve(gram + ridge * np.eye(len(train)), y[train] - y_mean)
            predicted[held_out] = xh @ (xt.T @ alpha) + y_mean
        error = ((predicted - y) ** 2).mean(0)
        r2 = 1.0 - error / variance
        if best is None or r2.mean() > best[0].mean():
            best = (r2, np.sqrt(error), float(ridge))
    assert best is not None
    return best


def first_frame_block_positions(reader: LeRobotReader, episodes: list[int]) -> np.ndarray:
    """True (x, y) [m] of every block (BLOCK_COLORS order) at the start of each episode, rebuilt from
    the episode's recorded `trivla/task` and `trivla/seed`: (N, 2 * len(BLOCK_COLORS))."""
    layout = Layout.default()
    rows = []
    for episode in episodes:
        row = reader.episodes[episode]
        for key in ("trivla/task", "trivla/seed"):
            if key not in row:
                raise ValueError(f"episode {episode} has no {key!r}: the dataset was not written by `collect`")
        spec, _ = sample_task_instance(get_task(row["trivla/task"]), np.random.default_rng(row["trivla/seed"]), layout)
        rows.append(np.concatenate([spec.blocks[c].position[:2] for c in BLOCK_COLORS]))
    return np.asarray(rows)


def first_frames(reader: LeRobotReader, episodes: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """The static and the wrist camera's first frame of each episode: uint8 (N, H, W, 3) each."""
    return tuple(np.stack([reader.episode_video(e, CAMERAS[key])[0] for e in episodes])
                 for key in ("static_rgb", "wrist_rgb"))


@torch.inference_mode()
def first_frame_features(
    model: TriVLA, frames: tuple[np.ndarray, np.ndarray], instructions: list[str], *, batch: int = 16
) -> dict:
    """Each feature set System 1 can read, from `first_frames` and each episode's instruction:
    name -> (N, D)."""
    static, wrist = frames
    pixels = resize_frames(static, PIXEL_REFERENCE_SIZE).reshape(len(static), -1).astype(np.float32)
    out: dict[str, list[np.ndarray]] = {}
    static_t = torch.from_numpy(resize_frames(static, model.image_size))
    wrist_t = torch.from_numpy(resize_frames(wrist, model.image_size))
    vl = model.vision_language
    # The static view's image tokens follow the prompt head, which is the same in every prompt.
    static_first = len(vl.build_prompts([[]], 2)[0].text_pieces[0]) if vl is not None else 0
    for start in range(0, len(static), batch):
        s, w = static_t[start : start + batch], wrist_t[start : start + batch]
        texts = instructions[start : start + batch]
        if vl is not None:
            tokens = vl.encode_images(s.to(model.device))
            out.setdefault("System 2 image tokens, static view (projector output)", []).append(tokens.flatten(1))
            q_vl, _ = model.encode_vision_language_batch(s, w, texts)
            static_q_vl = q_vl[:, static_first : static_first + tokens.shape[1]].flatten(1)
            out.setdefault(f"System 2 Q_vl, static-view tokens (LLM layer {vl.config.select_layer})", []).append(static_q_vl)
        if model.dynamics is not None:
            f_static, _ = model.encode_dynamics_batch(s, w, texts, generator=torch.Generator().manual_seed(start))
            out.setdefault("System 3 F_p, static view (all frames)", []).append(f_static.flatten(1))
    result = {name: torch.cat(parts).float().cpu().numpy() for name, parts in out.items()}
    result[f"pixels {PIXEL_REFERENCE_SIZE}x{PIXEL_REFERENCE_SIZE}, static view (reference)"] = pixels
    return result


@torch.inference_mode()
def first_frame_image_tokens(model: TriVLA, frames: tuple[np.ndarray, np.ndarray], *, batch: int = 16) -> np.ndarray:
    """System 2's projected image tokens of the static then the wrist view of `first_frames`:
    (N, 2 * tokens per view, D)."""
    views = [torch.from_numpy(resize_frames(f, model.image_size)) for f in frames]
    parts = [torch.cat([model.vision_language.encode_images(v[start : start + batch].to(model.device)) for v in views],
                       dim=1) for start in range(0, len(views[0]), batch)]
    return torch.cat(parts).float().cpu().numpy()


def probe_block_positions(
    model: TriVLA, reader: LeRobotReader, *, max_episodes: int | None = None, folds: int = 5,
    attention_steps: int = ATTENTION_PROBE_STEPS,
) -> list[ProbeResult]:
    """One ProbeResult per feature set, targets the (x, y) of every block at the first frame; with
    System 2 and `attention_steps` > 0 also its image tokens' attention read-outs (ridge: 0)."""
    episodes = list(range(reader.num_episodes if max_episodes is None else min(max_episodes, reader.num_episodes)))
    targets = first_frame_block_positions(reader, episodes)
    frames = first_frames(reader, episodes)
    results = []
    for name, features in first_frame_features(model, frames, [reader.task_of(e) for e in episodes]).items():
        r2, rmse, ridge = ridge_probe(features, targets, folds=folds)
        results.append(ProbeResult(name, int(features.shape[1]), r2.tolist(), rmse.tolist(), ridge))
    if model.vision_language is not None and attention_steps > 0:
        tokens = first_frame_image_tokens(model, frames)
        for positions in (False, True):
            r2, rmse = attention_probe(tokens, targets, positions=positions, steps=attention_steps)
            name = ("System 2 image tokens, both views, attention read-out per block "
                    + ("+ token positions" if positions else "(no token positions)"))
            results.append(ProbeResult(name, int(tokens.shape[1] * tokens.shape[2]), r2.tolist(), rmse.tolist(), 0.0))
    return results


def format_probe_table(results: list[ProbeResult], episodes: int) -> str:
    """Markdown: one row per feature set, R^2 and RMSE averaged over the blocks' x and y."""
    lines = [
        f"Probes of block positions at the first frame ({episodes} episodes; ridge rows: 5-fold linear "
        "ridge on the flattened features; attention rows: one learned query per block, 20% held out)",
        "",
        "| feature | dims | R^2 (x, y mean) | RMSE [cm] |",
        "| --- | --- | --- | --- |",
    ]
    for r in results:
        lines.append(f"| {r.feature} | {r.dims} | {r.mean_r2:.2f} | {100 * float(np.mean(r.rmse)):.1f} |")
    return "\n".join(lines)
