"""StepBatchSampler: ranks get disjoint shards, batches are a pure function of the step (resumable),
epochs reshuffle; TrainConfig checks and the learning-rate schedule."""

from __future__ import annotations

import pytest

from trivla_drake.config_io import with_flags
from trivla_drake.train.config import TrainConfig, check_resume_compatible
from trivla_drake.train.sampler import StepBatchSampler
from trivla_drake.train.trainer import learning_rate


def _epoch(sampler: StepBatchSampler, epoch: int) -> list[int]:
    return [i for s in range(epoch * sampler.steps_per_epoch, (epoch + 1) * sampler.steps_per_epoch)
            for i in sampler.batch_at(s)]


def test_ranks_get_disjoint_shards_covering_the_data():
    samplers = [StepBatchSampler(40, 4, seed=1, rank=r, world_size=2, total_steps=100) for r in range(2)]
    shards = [_epoch(s, 0) for s in samplers]
    assert len(shards[0]) == len(shards[1]) == 20
    assert set(shards[0]).isdisjoint(shards[1])
    assert set(shards[0]) | set(shards[1]) == set(range(40))


def test_uneven_data_is_padded_so_ranks_take_equal_steps():
    samplers = [StepBatchSampler(7, 2, seed=0, rank=r, world_size=2, total_steps=10) for r in range(2)]
    assert samplers[0].steps_per_epoch == samplers[1].steps_per_epoch == 2
    assert len(list(samplers[0])) == len(list(samplers[1])) == 10


def test_batches_depend_only_on_the_step():
    full = list(StepBatchSampler(30, 4, seed=3, total_steps=20))
    resumed = list(StepBatchSampler(30, 4, seed=3, start_step=13, total_steps=20))
    assert resumed == full[13:]
    assert list(StepBatchSampler(30, 4, seed=4, total_steps=20)) != full


def test_epochs_are_reshuffled_and_each_covers_every_sample():
    sampler = StepBatchSampler(24, 4, seed=0, total_steps=100)
    first, second = _epoch(sampler, 0), _epoch(sampler, 1)
    assert sorted(first) == sorted(second) == list(range(24))
    assert first != second


def test_a_dataset_smaller_than_a_batch_still_gives_full_batches():
    sampler = StepBatchSampler(3, 8, seed=0, total_steps=2)
    assert [len(b) for b in sampler] == [8, 8]
    with pytest.raises(ValueError, match="no training samples"):
        StepBatchSampler(0, 8, seed=0, total_steps=2)


def test_config_fills_stage_defaults_and_rejects_bad_values():
    config = TrainConfig(stage="policy", out="o", data="d").resolved()
    assert config.batch_size == 32 and config.lr == 1e-4 and config.cache_dir
    config.validate()
    with pytest.raises(ValueError, match="stage must be one of"):
        TrainConfig(stage="audio", out="o").resolved()
    with pytest.raises(ValueError, match="data .*required"):
        TrainConfig(stage="video", out="o").resolved().validate()
    with pytest.raises(ValueError, match="video stage trains System 3: it cannot run with use_system3 false"):
        TrainConfig(stage="video", out="o", data="d", use_system3=False).resolved().validate()
    with pytest.raises(ValueError, match="batch_size"):
        TrainConfig(stage="vlm", out="o", batch_size=0).resolved().validate()


def test_resume_may_extend_steps_but_not_change_what_is_learned():
    saved = TrainConfig(stage="policy", out="o", data="d", preset="tiny").resolved()
    check_resume_compatible(saved, TrainConfig(stage="policy", out="o", data="d", preset="tiny", steps=99,
                                               resume=True).resolved())
    with pytest.raises(ValueError, match=r"cannot resume: lr was"):
        check_resume_compatible(saved, TrainConfig(stage="policy", out="o", data="d", preset="tiny",
                                                   lr=1.0).resolved())


def test_learning_rate_warms_up_then_decays_by_cosine():
    config = with_flags(TrainConfig(stage="policy", out="o", data="d", steps=110, lr=1.0),
                        {"optimizer.warmup_steps": 10, "optimizer.min_lr_ratio": 0.1}).resolved()
    assert learning_rate(config, 0) == pytest.approx(0.1)
    assert learning_rate(config, 9) == pytest.approx(1.0)
    assert learning_rate(config, 60) == pytest.approx(0.55)
    assert learning_rate(config, 110) == pytest.approx(0.1)
    values = [learning_rate(config, s) for s in range(10, 111)]
    assert all(a >= b for a, b in zip(values, values[1:]))
