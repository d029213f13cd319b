"""The refit job (train/refit_job.py): the shipped lineage's last stage re-fits a checkpoint's grounding read-out alone,
reports the sub-goal's errors before and after, writes the model atomically and the same bytes for the same settings,
loads its config typed from YAML and names the field of a bad setting before any model loads."""

import dataclasses
import json
import math

import pytest
import torch

from trivla_drake.train import grounding_refit as refit
from trivla_drake.train.export_job import holds_export_of
from trivla_drake.train.refit_job import RefitConfig, check_refit_config, report_path, run_refit


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """(checkpoint, data): a tiny model with an instruction grounding and a two-episode dataset with tcp poses."""
    import numpy as np
    from test_grounding_scenes import _grounded_model

    from trivla_drake.nn.checkpoint import save_checkpoint
    from trivla_drake.nn.normalization import NormalizationStats
    from trivla_drake.train.synthetic import write_synthetic_dataset

    root = tmp_path_factory.mktemp("refit")
    model = _grounded_model()
    rng = np.random.default_rng(0)
    model.set_normalization(NormalizationStats.from_data(rng.normal(size=(50, 18)), rng.uniform(-0.05, 0.05, (50, 10, 7))))
    save_checkpoint(model, str(root / "in"))
    data = write_synthetic_dataset(root / "d", episodes=2, length=10, image_size=16, tcp_pose=True)
    return str(root / "in"), str(data)


@pytest.fixture
def config(inputs, tmp_path, monkeypatch):
    """A few scenes and steps of the job on `inputs`, writing to tmp_path/out; its cache in tmp_path/cache."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    checkpoint, data = inputs
    return RefitConfig(checkpoint=checkpoint, data=data, out=str(tmp_path / "out"), scenes=4, test_scenes=2, steps=3,
                       lr=0.01, threads=1)


def test_the_job_refits_the_grounding_readout_alone_and_reports_its_errors_before_and_after(config, tmp_path):
    from trivla_drake.nn import load_checkpoint

    report = run_refit(config, progress=False)
    assert report == json.loads((tmp_path / "out.refit.json").read_text())
    assert report["config"] == dataclasses.asdict(config)
    assert report["samples"] == {"scenes": 4, "test_scenes": 2, "data_frames": 4}
    errors = report["median_and_p90_xy_error_cm"]
    for when in ("before", "after"):
        assert set(errors[when]) == {"test_scenes", "data_frames"}
        assert set(errors[when]["test_scenes"]) == {"all", "lift_block"}
        assert all(0 <= median <= p90 for median, p90 in errors[when]["test_scenes"].values())
        assert set(report["median_z_error_cm"][when]) == {"test_scenes"}
    assert errors["before"] != errors["after"]
    assert [step for step, _ in report["loss_ema"]] == [3] and math.isfinite(report["loss_ema"][0][1])
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["config.json", "model.safetensors",
                                                                    "refit_config.yaml"]
    assert holds_export_of(config.out, config, "refit_config.yaml")  # the job's config beside its model
    # The saved model differs from the input only in the read-out (every weight rounded to float16).
    before = load_checkpoint(config.checkpoint).state_dict()
    after = load_checkpoint(config.out).state_dict()
    readout = {f"policy.{name}" for name in refit.readout_parameters(load_checkpoint(config.checkpoint))}
    changed = {k for k, v in after.items() if not torch.equal(v, before[k].to(torch.float16).to(v.dtype))}
    assert changed and changed <= readout
    assert not any(p.name.startswith((".tmp", ".old")) for p in tmp_path.iterdir())  # nothing half-written left


def test_the_same_settings_give_the_same_bytes_with_or_without_the_cached_q_vl(config, tmp_path, capsys):
    run_refit(config, progress=False)
    first = (tmp_path / "out" / "model.safetensors").read_bytes()
    run_refit(config, progress=True)  # into the earlier export: replaced; the three sets' Q_vl read from the cache
    assert capsys.readouterr().out.count("Q_vl of") == 3
    assert (tmp_path / "out" / "model.safetensors").read_bytes() == first
    run_refit(dataclasses.replace(config, q_vl_cache=False, out=str(tmp_path / "fresh")), progress=False)
    assert (tmp_path / "fresh" / "model.safetensors").read_bytes() == first
    run_refit(dataclasses.replace(config, out=str(tmp_path / "longer"), steps=4), progress=False)
    assert (tmp_path / "longer" / "model.safetensors").read_bytes() != first  # the bytes can tell runs apart


def test_the_q_vl_cache_is_keyed_by_the_weights_and_config_alone(config, tmp_path, capsys):
    """A checkpoint with tokenizer folders and a run's training state beside its weights is read (no folder is read as
    a file) and keyed by its config.json and weights alone: a copy with them added finds the original's Q_vl."""
    import shutil

    run_refit(config, progress=False)
    copy = tmp_path / "copy"
    shutil.copytree(config.checkpoint, copy)
    (copy / "tokenizer_vision_language").mkdir()
    (copy / "tokenizer_vision_language" / "tokenizer.json").write_text("{}")
    (copy / "training_state.pt").write_bytes(b"optimizer")
    capsys.readouterr()
    run_refit(dataclasses.replace(config, checkpoint=str(copy), out=str(tmp_path / "out2")), progress=True)
    assert capsys.readouterr().out.count("Q_vl of") == 3


def test_the_config_loads_typed_from_yaml():
    from pydrake.common.yaml import yaml_load_typed

    loaded = yaml_load_typed(schema=RefitConfig, data="checkpoint: runs/soup3\ndata: data/sim\nout: models/x\n"
                                                      "scenes: 40\nlr: 0.001\nreport: r.json\n")
    assert loaded == RefitConfig(checkpoint="runs/soup3", data="data/sim", out="models/x", scenes=40, lr=0.001,
                                 report="r.json")
    assert yaml_load_typed(schema=RefitConfig, data="out: m\n").report is None
    assert report_path(RefitConfig(out="models/x/")) == "models/x.refit.json"
    with pytest.raises(ValueError, match="'many'"):
        yaml_load_typed(schema=RefitConfig, data="scenes: many\n")
    with pytest.raises(RuntimeError, match="chain_starts"):  # an experiment's option is no field of the product job
        yaml_load_typed(schema=RefitConfig, data="chain_starts: 0.5\n")


@pytest.mark.parametrize("change, message", [
    ({"checkpoint": ""}, "checkpoint must name a folder"),
    ({"data": "no/such/dataset"}, "data no/such/dataset is not a folder"),
    ({"out": ""}, "out must name a folder"),
    ({"scenes": 0}, "scenes must be an integer >= 1; got 0"),
    ({"test_scenes": 2.5}, "test_scenes must be an integer >= 1; got 2.5"),
    ({"stride": 0}, "stride must be an integer >= 1"),
    ({"steps": True}, "steps must be an integer >= 1"),
    ({"threads": 0}, "threads must be an integer >= 1"),
    ({"lr": 0.0}, "lr must be a finite number > 0"),
    ({"lr": float("nan")}, "lr must be a finite number > 0"),
    ({"weights_dtype": "int8"}, "weights_dtype must be one of float32, float16, bfloat16; got 'int8'"),
    ({"report": "OUT/report.json"}, "report .* lies in out"),
])
def test_a_bad_setting_is_named_before_any_model_loads(config, tmp_path, monkeypatch, change, message):
    if change.get("report"):
        change = {"report": str(tmp_path / "out" / "report.json")}

    def no_load(*args, **kwargs):
        raise AssertionError("a model was loaded")

    monkeypatch.setattr("trivla_drake.nn.load_checkpoint", no_load)
    with pytest.raises(ValueError, match=message):
        run_refit(dataclasses.replace(config, **change), progress=False)
    check_refit_config(config)  # the unchanged settings are fine


def test_an_output_folder_of_other_things_is_refused_and_a_checkpoint_without_grounding_named(config, tmp_path, saved):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="out .* is not empty .*pass overwrite to replace it"):
        run_refit(config, progress=False)
    assert (tmp_path / "out" / "notes.txt").read_text() == "mine"
    with pytest.raises(ValueError, match="has no instruction grounding to re-fit"):
        run_refit(dataclasses.replace(config, checkpoint=saved[1], overwrite=True), progress=False)
    assert (tmp_path / "out" / "notes.txt").read_text() == "mine"  # nothing written when the job fails
