"""`train`'s ema_decay: checkpoints hold the moving average of the trained weights; a killed run resumes
to the same average and trained weights."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from torch import nn

from trivla_drake.config_io import with_flags
from trivla_drake.nn import load_checkpoint
from trivla_drake.train import TrainConfig, train
from trivla_drake.train import checkpoints as ckpt
from trivla_drake.train.synthetic import write_synthetic_dataset
from trivla_drake.train.weight_average import WeightAverage, ramped_decay


def test_the_average_follows_the_ramped_decay_and_swaps_back():
    layer = nn.Linear(2, 1)
    frozen = nn.Linear(2, 1).requires_grad_(False)
    module = nn.ModuleDict({"trained": layer, "frozen": frozen})
    average = WeightAverage(module, 0.9)
    assert set(average.params) == {"trained.weight", "trained.bias"}
    expected = layer.weight.detach().clone()
    for n, value in enumerate([1.0, 2.0, 3.0]):
        with torch.no_grad():
            layer.weight.fill_(value)
        average.update()
        d = ramped_decay(0.9, n)
        expected = d * expected + (1 - d) * value
    assert ramped_decay(0.9, 0) == pytest.approx(0.1) and ramped_decay(0.9, 1000) == 0.9
    torch.testing.assert_close(average.average["trained.weight"], expected)
    with average.swapped_in():
        torch.testing.assert_close(layer.weight.detach(), expected)
    assert torch.all(layer.weight == 3.0)


def test_bad_decay_and_a_module_without_trained_weights_are_refused():
    with pytest.raises(ValueError, match="ema_decay"):
        WeightAverage(nn.Linear(2, 1), 1.0)
    with pytest.raises(ValueError, match="no trained parameters"):
        WeightAverage(nn.Linear(2, 1).requires_grad_(False), 0.9)
    with pytest.raises(ValueError, match="ema_decay"):
        TrainConfig(stage="policy", out="x", data="d", ema_decay=-0.1, steps=1, batch_size=1, lr=1.0).validate()


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("ema")
    return {"data": write_synthetic_dataset(root / "data", episodes=2, length=16, image_size=16),
            "cache": str(root / "cache")}


def _config(out, data, **kw):
    return with_flags(TrainConfig(stage="policy", out=str(out), data=data["data"], preset="tiny", steps=6,
                                  batch_size=2, checkpoint_every=2, cache_dir=data["cache"], progress=False, lr=1e-3, ema_decay=0.5, **kw), {"optimizer.warmup_steps": 1})


class Killed(Exception):
    pass


def _policy_weights(path):
    return {k: v for k, v in load_checkpoint(str(path)).state_dict().items() if k.startswith("policy.")}


def test_checkpoints_hold_the_average_and_resume_to_the_same_run(data, tmp_path):
    reference = train(_config(tmp_path / "ref", data))
    state = ckpt.load_train_state(tmp_path / "ref" / "final")["weight_average"]
    assert state["updates"] == 6
    saved = _policy_weights(tmp_path / "ref" / "final")
    assert state["average"] and all(torch.equal(saved[k], v) for k, v in state["average"].items())
    assert any(not torch.equal(state["average"][k], state["trained"][k]) for k in state["average"])

    def kill(step):
        if step == 5:
            raise Killed
    with pytest.raises(Killed):
        train(_config(tmp_path / "run", data), step_callback=kill)  # last checkpoint: step 4
    resumed = train(_config(tmp_path / "run", data, resume=True))
    assert resumed["weights_sha256_per_rank"] == reference["weights_sha256_per_rank"]  # the trained weights
    assert all(torch.equal(a, b) for a, b in zip(_policy_weights(tmp_path / "run" / "final").values(),
                                                 saved.values()))


def test_a_changed_decay_is_refused_on_resume(data, tmp_path):
    train(dataclasses.replace(_config(tmp_path / "plain", data), ema_decay=0.0))
    with pytest.raises(ValueError, match="ema_decay"):
        train(dataclasses.replace(_config(tmp_path / "plain", data), steps=8, resume=True))
