"""Fits System 1's feature standardisers (nn/feature_standardizer.py) on the cached System 2/3
features of the training episodes, once at the start of a policy run (a resumed run keeps the
statistics saved in its checkpoint)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from trivla_drake.nn.feature_standardizer import MomentAccumulator
from trivla_drake.nn.trivla import TriVLA

_VIEW_KEYS = ("dynamics_static", "dynamics_wrist")


def fit_feature_standardizers(model: TriVLA, shards: dict[int, Path], *, progress: bool = False) -> dict[str, Any]:
    """Per-element mean/std of every cached frame's Q_vl (per prompt position) and F_p (per view),
    set on the model's System 1. Returns a summary for the run's summary.json."""
    from safetensors import safe_open
    from tqdm import tqdm

    policy = model.policy
    if not shards or not (policy.uses_vl or policy.uses_dynamics):
        return {"feature_statistics_frames": 0}
    vl_acc = MomentAccumulator(policy.vl_standardizer.shape) if policy.uses_vl else None
    view_accs = [MomentAccumulator(s.shape) for s in policy.dynamics_standardizers] if policy.uses_dynamics else []
    frames = 0
    for episode in tqdm(sorted(shards), desc="feature statistics", unit="episode", disable=not progress):
        with safe_open(str(shards[episode]), framework="pt", device="cpu") as handle:
            if vl_acc is not None:
                q_vl = handle.get_tensor("q_vl").float()
                fixed = policy.vl_standardizer.positions
                if q_vl.shape[1] <= fixed:
                    raise ValueError(f"cached Q_vl of episode {episode} has {q_vl.shape[1]} tokens; the prompt "
                                     f"head and image tokens alone are {fixed}: the cache does not fit this model")
                vl_acc.add(q_vl[:, :fixed], rows=slice(0, fixed))
                vl_acc.add(q_vl[:, fixed:].reshape(-1, 1, q_vl.shape[-1]), rows=slice(fixed, fixed + 1))
            for acc, key in zip(view_accs, _VIEW_KEYS):
                features = handle.get_tensor(key).float()
                acc.add(features.flatten(0, 1))  # the T+1 frames share statistics
            frames += handle.get_slice("frame_index").get_shape()[0]
    with torch.no_grad():
        if vl_acc is not None:
            policy.vl_standardizer.fit(*vl_acc.mean_std())
        if view_accs:
            for standardizer, acc in zip(policy.dynamics_standardizers, view_accs):
                standardizer.fit(*acc.mean_std())
    return {"feature_statistics_frames": frames}
