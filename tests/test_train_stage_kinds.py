"""The training jobs as recipe stage kinds (train/stage_kinds.py): each kind's is_done holds once its output is
complete and made by this very config (for a training run: one this config may resume), its describe is the
equivalent command line; and the flat training config of before reads as the same nested config."""

from __future__ import annotations

import dataclasses
import shlex

import pytest
import yaml

from trivla_drake.config_io import load_config, with_flags
from trivla_drake.recipe import registered_stage_kinds
from trivla_drake.train import TrainConfig, train
from trivla_drake.train.export_job import ExportConfig, SoupConfig, holds_model_export, run_export, run_soup
from trivla_drake.train.refit_job import RefitConfig
from trivla_drake.train.stage_kinds import describe_train, train_stage_done
from trivla_drake.train.synthetic import write_synthetic_dataset


def _kind(name):
    from trivla_drake.recipe import _KINDS

    return _KINDS[name]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A finished 2-step policy run of a tiny model: (its config, the dataset)."""
    root = tmp_path_factory.mktemp("kinds")
    data = write_synthetic_dataset(root / "data", episodes=2, length=12, image_size=16)
    config = with_flags(TrainConfig(stage="policy", data=data, out=str(root / "run"), preset="tiny", steps=2,
                                    batch_size=2, cache_dir=str(root / "cache"), progress=False),
                        {"features.stride": 2, "optimizer.warmup_steps": 1})
    summary = train(config)
    return config, data, summary


def test_the_four_kinds_are_registered_with_their_config_schemas():
    assert {"train", "export", "soup", "refit"} <= set(registered_stage_kinds())
    assert [_kind(name).schema for name in ("train", "export", "soup", "refit")] == [
        TrainConfig, ExportConfig, SoupConfig, RefitConfig]


def test_train_is_done_once_final_holds_the_last_step(tiny_run, tmp_path):
    config, _, _ = tiny_run
    assert train_stage_done(config, str(tmp_path))
    assert not train_stage_done(dataclasses.replace(config, steps=3), str(tmp_path))  # a longer run is not done
    assert not train_stage_done(dataclasses.replace(config, out=str(tmp_path / "none")), str(tmp_path))
    # a run another config made is not this config's: a changed lr is not done; a change a resume allows is
    assert not train_stage_done(with_flags(config, {"lr": config.resolved().lr * 2}), str(tmp_path))
    assert train_stage_done(dataclasses.replace(config, threads=1), str(tmp_path))
    # the run folder holds the run's full config as YAML, which --config reads back as the same config
    saved = load_config(TrainConfig, f"{config.out}/train_config.yaml")
    assert dataclasses.replace(saved, cache_dir=config.cache_dir) == config.resolved()


def test_train_describe_is_a_command_line_with_set_for_the_other_fields():
    config = with_flags(TrainConfig(stage="policy", data="d d", out="runs/p", init="runs/v/final", steps=30),
                        {"policy.grounding.weight": 1.0, "policy.grounding.carry_tasks": ["stack_block"],
                         "features.stride": 3, "threads": 2})
    line = describe_train(config)
    assert shlex.split(line) == [
        "trivla-drake", "train", "--stage", "policy", "--out", "runs/p", "--data", "d d", "--init", "runs/v/final",
        "--steps", "30", "--threads", "2", "--set", "features.stride=3", "--set", "policy.grounding.weight=1.0",
        "--set", 'policy.grounding.carry_tasks=["stack_block"]']
    assert _kind("train").describe(config) == line


def test_export_and_soup_are_done_only_for_a_folder_their_config_wrote(tiny_run, tmp_path):
    config, _, summary = tiny_run
    export = ExportConfig(checkpoint=summary["final_checkpoint"], out=str(tmp_path / "export"), dtype="float32")
    assert not _kind("export").is_done(export, str(tmp_path))
    run_export(export)
    names = sorted(p.name for p in (tmp_path / "export").iterdir())
    assert names == ["config.json", "export_config.yaml", "model.safetensors"] and holds_model_export(export.out)
    assert yaml.safe_load((tmp_path / "export" / "export_config.yaml").read_text())["dtype"] == "float32"
    assert _kind("export").is_done(export, str(tmp_path))
    assert not _kind("export").is_done(dataclasses.replace(export, dtype="float16"), str(tmp_path))
    assert _kind("export").describe(export) == (f"trivla-drake export {export.checkpoint} --out {export.out} "
                                                "--set dtype=float32")
    soup = SoupConfig(checkpoints=[summary["final_checkpoint"], export.out], out=str(tmp_path / "soup"))
    assert not _kind("soup").is_done(soup, str(tmp_path))
    run_soup(soup)
    assert _kind("soup").is_done(soup, str(tmp_path))
    assert not _kind("soup").is_done(dataclasses.replace(soup, drop_unused_llm_layers=True), str(tmp_path))
    assert _kind("soup").describe(soup).startswith(f"trivla-drake soup {summary['final_checkpoint']} {export.out} ")


def test_refit_is_done_for_its_model_folder_and_described_with_its_data(tmp_path):
    refit = RefitConfig(checkpoint="runs/soup", data="data/sim", out=str(tmp_path / "model"), steps=10)
    assert not _kind("refit").is_done(refit, str(tmp_path))
    assert _kind("refit").describe(refit) == (f"trivla-drake refit runs/soup --data data/sim --out {refit.out} "
                                              "--set steps=10")


def test_the_flat_config_of_before_reads_as_the_nested_config(tiny_run):
    """The tiny policy run given by the old field names (a train_config.json of before) is the same config as the
    one given by the dotted fields (so it trains the same run)."""
    config, data, _ = tiny_run
    flat = {"stage": "policy", "data": data, "out": config.out, "preset": "tiny", "steps": 2,
            "batch_size": 2, "cache_dir": config.cache_dir, "progress": False, "feature_stride": 2,
            "warmup_steps": 1}
    assert TrainConfig.from_dict(flat) == config
