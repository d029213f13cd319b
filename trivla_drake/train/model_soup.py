"""A uniform weight average ("model soup") of models trained from one start.

Follow runs that differ only in their seed land up to 0.08 apart in closed-loop success
(research/follow_seeds): each one's System 1 is one draw. Their weights, fine-tuned for a few thousand
steps from the same checkpoint, lie close together (max |difference| 0.05 there), and the average of
such weights is a model of its own, with one model's cost at run time (Wortsman et al. 2022, "Model
soups"). Only trained parameters are averaged: buffers (the feature standardizers' statistics, fitted
on the frozen systems' features) and the frozen Systems 2 and 3 must be the same in every model, else
the average would pair one model's features with another's statistics.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

FROZEN_PREFIXES = ("vision_language.", "dynamics.")  # Systems 2 and 3: frozen while System 1 trains
# How the weights are stored, not what they are: an export (float16) soups with the float32 runs followed from it.
STORAGE_ONLY_FIELDS = ("weights_dtype",)


def soup_state_dict(models: list[torch.nn.Module], names: list[str] | None = None) -> dict[str, torch.Tensor]:
    """The uniform average of `models`' parameters, in float32, with their buffers and frozen systems (which
    must be equal in all). `names` label the models in errors (default: model 0, model 1, ...)."""
    if len(models) < 2:
        raise ValueError(f"a soup needs at least 2 models; got {len(models)}")
    names = names if names is not None else [f"model {i}" for i in range(len(models))]
    if len(names) != len(models):
        raise ValueError(f"names must label every model: {len(names)} names for {len(models)} models")
    first = models[0].state_dict()
    parameters = {name for name, _ in models[0].named_parameters()}
    total = {key: value.detach().float().clone() if key in parameters else value for key, value in first.items()}
    for model, label in zip(models[1:], names[1:]):
        state = model.state_dict()
        if set(state) != set(first):
            extra, missing = sorted(set(state) - set(first)), sorted(set(first) - set(state))
            raise ValueError(f"{label} has other tensors than {names[0]}: extra {extra[:3]}, missing {missing[:3]}")
        for key, value in state.items():
            if value.shape != first[key].shape:
                raise ValueError(f"{key}: {label} has shape {tuple(value.shape)}, {names[0]} "
                                 f"{tuple(first[key].shape)}")
            must_match = key not in parameters or key.startswith(FROZEN_PREFIXES)
            if must_match and not torch.equal(value, first[key]):
                what = "a buffer" if key not in parameters else "a frozen System 2 or 3 weight"
                raise ValueError(f"{key} ({what}) differs between {names[0]} and {label}: a soup averages models "
                                 "trained from one start on the same frozen Systems 2 and 3")
            if key in parameters:
                total[key] += value.detach().float()
    return {key: value / len(models) if key in parameters else value for key, value in total.items()}


def _config_of(checkpoint: Path) -> dict:
    return json.loads((checkpoint / "config.json").read_text())


def soup_checkpoints(
    sources: list[str | os.PathLike],
    target: str | os.PathLike,
    *,
    weights_dtype: str = "float16",
    drop_unused_llm_layers: bool = False,
    job_config: tuple[str, Any] | None = None,
) -> Path:
    """Writes the soup of checkpoints `sources` (same config.json, e.g. runs' final/ folders) to `target`
    atomically, as `export_checkpoint` writes one model (`job_config`: as there)."""
    from trivla_drake.nn.checkpoint import load_checkpoint
    from trivla_drake.train.checkpoints import write_model_folder

    paths = [Path(source) for source in sources]
    if len(paths) < 2:
        raise ValueError(f"a soup needs at least 2 checkpoints; got {len(paths)}")
    for path in paths:
        if not (path / "config.json").is_file():
            raise FileNotFoundError(f"{path} is not a checkpoint folder (no config.json)")
    reference = _config_of(paths[0])
    for path in paths[1:]:
        config = _config_of(path)
        differing = sorted(key for key in set(reference) | set(config)
                           if reference.get(key) != config.get(key) and key not in STORAGE_ONLY_FIELDS)
        if differing:
            raise ValueError(f"{path}'s config.json differs from {paths[0]}'s in {', '.join(differing)}: a soup "
                             "averages models of one config")
    models = [load_checkpoint(str(path)) for path in paths]
    averaged = soup_state_dict(models, [str(path) for path in paths])
    model = models[0]
    model.load_state_dict(averaged)
    if drop_unused_llm_layers and model.vision_language is not None:
        model.vision_language.drop_layers_above_readout()
    return write_model_folder(target, model, weights_dtype=weights_dtype, job_config=job_config)
