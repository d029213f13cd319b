"""Training noise on the sub-goal System 1 reads (`TrainConfig.subgoal_noise`, `--subgoal-noise`): the offset
encoder sees the grounding's sub-goal moved along x and y by Gaussian noise of the asked standard deviation [m],
never in height; the grounding's own loss and inference see the sub-goal as predicted; bad settings are refused
naming the field."""

import dataclasses

import numpy as np
import pytest
import torch

from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.config import make_config
from trivla_drake.nn.panda_tcp import denormalize_position
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.train.config import TrainConfig


def _model(offset: bool = True) -> TriVLA:
    torch.manual_seed(0)
    config = make_config("tiny")
    return TriVLA(dataclasses.replace(config, policy=dataclasses.replace(
        config.policy, tcp_features=True, instruction_grounding=True, subgoal_offset=offset))).eval()


def _batch(model: TriVLA, rows: int = 2) -> dict:
    obs = example_observation()
    pol = model.config.policy
    return {
        "static_rgb": np.stack([obs["static_rgb"]] * rows), "wrist_rgb": np.stack([obs["wrist_rgb"]] * rows),
        "instruction": ["lift the red block"] * rows,
        "state": torch.zeros(rows, pol.state_dim),
        "action": torch.zeros(rows, pol.action_horizon, pol.action_dim),
        "subgoal_position": torch.tensor([[0.5, 0.1, 0.03]] * rows),
    }


def _offset_inputs(model: TriVLA, run) -> tuple[torch.Tensor, torch.Tensor, object]:
    """While `run()` runs: the sub-goal the offset encoder read and the one the grounding predicted [m] (B, 3)
    of its first call; and what `run` returned."""
    read, predicted = [], []
    hook = model.policy.subgoal_offset.register_forward_hook(lambda module, args, out: read.append(args[0].detach()))
    original = model.policy._ground

    def ground(*args):
        goal, subgoal = original(*args)
        predicted.append(subgoal.detach())
        return goal, subgoal

    model.policy._ground = ground
    try:
        result = run()
    finally:
        hook.remove()
        del model.policy._ground
    assert len(read) == len(predicted) == 1
    return denormalize_position(read[0]), denormalize_position(predicted[0][:, :3]), result


def _loss_inputs(model: TriVLA, batch: dict, noise: float) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """`_offset_inputs` of one flow-matching loss with `noise` [m], and the loss's info."""
    read, predicted, (_, info) = _offset_inputs(
        model, lambda: model.compute_loss(batch, generator=torch.Generator().manual_seed(1), subgoal_noise=noise))
    return read, predicted, info


def test_the_offset_encoder_reads_the_subgoal_moved_along_x_and_y_only():
    model = _model()
    batch = _batch(model)
    read, predicted, info = _loss_inputs(model, batch, 0.0)
    assert torch.equal(read, predicted)
    read, predicted, noisy_info = _loss_inputs(model, batch, 0.03)
    moved = read - predicted
    assert (moved[:, :2].abs() > 1e-4).all() and torch.equal(moved[:, 2], torch.zeros(2))
    # the grounding's own loss reads the sub-goal as it predicted it
    assert noisy_info["grounding_loss"] == info["grounding_loss"]


def test_the_noise_has_the_asked_standard_deviation_in_metres():
    model = _model()
    shift = model._subgoal_shift(20000, 0.03, torch.Generator().manual_seed(0))
    metres = denormalize_position(shift) - denormalize_position(torch.zeros(3))
    np.testing.assert_allclose(metres[:, :2].std(0).numpy(), [0.03, 0.03], rtol=0.03)
    np.testing.assert_allclose(metres[:, :2].mean(0).numpy(), [0.0, 0.0], atol=1e-3)
    assert torch.equal(metres[:, 2], torch.zeros(20000))
    assert model._subgoal_shift(4, 0.0, None) is None


def test_inference_reads_the_subgoal_as_predicted():
    model = _model()
    read, predicted, _ = _offset_inputs(model, lambda: model.predict_action_chunk(example_observation(), seed=3))
    assert torch.equal(read, predicted)


def test_noise_on_a_model_without_an_offset_encoder_is_refused():
    model = _model(offset=False)
    with pytest.raises(ValueError, match="subgoal_noise.*policy.subgoal_offset is off"):
        model.compute_loss(_batch(model), generator=torch.Generator().manual_seed(1), subgoal_noise=0.02)
    with pytest.raises(ValueError, match="subgoal_noise must be a finite standard deviation"):
        _model().compute_loss(_batch(model), subgoal_noise=float("nan"))


def test_bad_settings_are_refused_naming_the_field(tmp_path):
    follow = dict(stage="policy", data=str(tmp_path), out=str(tmp_path / "o"), grounding_weight=1.0,
                  grounding_phase="follow", subgoal_offset=True, init=str(tmp_path / "init"))
    for phase in ("follow", "joint"):
        TrainConfig(**{**follow, "grounding_phase": phase}, subgoal_noise=0.02).resolved().validate()
    for bad in (-0.01, float("nan"), float("inf"), 0.5):
        with pytest.raises(ValueError, match=r"subgoal_noise \(--subgoal-noise\) is a standard deviation in metres"):
            TrainConfig(**follow, subgoal_noise=bad).resolved().validate()
    no_grounding = dict(grounding_weight=0.0, subgoal_offset=False, grounding_phase="joint")
    for change in (dict(grounding_phase="bind"), no_grounding):
        with pytest.raises(ValueError, match=r"subgoal_noise \(--subgoal-noise\).*a joint or follow run"):
            TrainConfig(**{**follow, **change}, subgoal_noise=0.02).resolved().validate()


def test_a_fresh_model_without_an_offset_encoder_is_refused_before_training(tmp_path):
    from trivla_drake.train.trainer import build_model

    config = TrainConfig(stage="policy", data=str(tmp_path), out=str(tmp_path / "o"), preset="tiny", grounding_weight=1.0,
                         subgoal_noise=0.02).resolved()
    with pytest.raises(ValueError, match=r"subgoal_noise \(--subgoal-noise\).*preset 'tiny' has none.*--subgoal-offset"):
        build_model(config, None)
    assert build_model(dataclasses.replace(config, subgoal_offset=True), None).policy.subgoal_offset is not None
