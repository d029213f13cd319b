"""recipes/trivla_cpu.yaml, the shipped model's recipe: loads typed, every stage's kind registered, the plan ends in
the shipped model and its tables; and the copy_dataset kind its extended datasets start from."""

import json
from pathlib import Path

import pytest

from trivla_drake.config_io import ConfigError
from trivla_drake.data.dataset_copy import DatasetCopyConfig, copy_dataset, dataset_copy_done
from trivla_drake.recipe import load_recipe, run_recipe
from trivla_drake.recipe_kinds import register_all

RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "trivla_cpu.yaml"


@pytest.fixture(scope="module")
def recipe():
    register_all()
    return load_recipe(RECIPE)


def test_the_recipe_loads_typed_with_every_kind_registered(recipe):
    kinds = [stage.kind for stage in recipe.stages]
    assert set(kinds) == {"collect", "copy_dataset", "train", "export", "soup", "refit", "tables"}
    assert kinds.count("train") == 25 and kinds.count("collect") == 9
    names = [stage.name for stage in recipe.stages]
    refit = recipe.stages[names.index("refit")]
    assert refit.config.out == "${workdir}/models/trivla_cpu" and refit.config.scenes == 12000
    assert recipe.stages[-1].kind == "tables" and recipe.stages[-1].config.checkpoints["full"] == refit.config.out


def test_the_dry_run_plans_every_stage_and_runs_nothing(recipe, tmp_path, capsys):
    recipe.workdir = str(tmp_path / "run")
    statuses = run_recipe(recipe, dry_run=True)
    assert list(statuses) == [stage.name for stage in recipe.stages]
    assert set(statuses.values()) == {"pending"}
    plan = capsys.readouterr().out
    assert "trivla-drake refit " + str(tmp_path / "run" / "runs" / "soup3") in plan
    assert "--set perturbation.name=dart" in plan and "policy.grounding.phase=bind" in plan
    assert not (tmp_path / "run").exists()


def test_a_typo_in_a_stage_names_the_stage_and_the_field(tmp_path):
    register_all()
    text = RECIPE.read_text().replace("episodes_per_task: 20", "episodes_per_tsk: 20", 1)
    (tmp_path / "bad.yaml").write_text(text)
    with pytest.raises(ConfigError, match="clean240.*episodes_per_tsk"):
        load_recipe(tmp_path / "bad.yaml")


def test_copy_dataset_copies_once_and_never_touches_an_existing_copy(tmp_path):
    from trivla_drake.train.synthetic import write_synthetic_dataset

    tiny_dataset = write_synthetic_dataset(tmp_path / "data", episodes=1, length=4, image_size=16)
    config = DatasetCopyConfig(source=str(tiny_dataset), dest=str(tmp_path / "copy"))
    assert not dataset_copy_done(config)
    copy_dataset(config)
    assert dataset_copy_done(config)
    info = json.loads((tmp_path / "copy" / "meta" / "info.json").read_text())
    assert info == json.loads((Path(tiny_dataset) / "meta" / "info.json").read_text())
    (tmp_path / "copy" / "extended").write_text("later stages extend the copy")
    with pytest.raises(ValueError, match="DatasetCopyConfig.dest .* exists already"):
        copy_dataset(config)
    assert (tmp_path / "copy" / "extended").read_text() == "later stages extend the copy"
    with pytest.raises(ValueError, match="not a LeRobot dataset|info.json"):
        copy_dataset(DatasetCopyConfig(source=str(tmp_path / "nowhere"), dest=str(tmp_path / "c2")))


def test_the_next_models_recipe_collects_4080_and_trains_on_the_minilm(tmp_path, capsys):
    register_all()
    recipe = load_recipe(RECIPE.parent / "trivla_next.yaml")
    stages = {stage.name: stage for stage in recipe.stages}
    collects = [stage for stage in recipe.stages if stage.kind == "collect"]
    # two datasets, each resumed stage after stage: all demonstrations, and 10% of them in the same mix (Table 1)
    full = [stage for stage in collects if stage.config.out == stages["joint"].config.data]
    tenth = [stage for stage in collects if stage.config.out == stages["data10_joint"].config.data]
    assert len(full) + len(tenth) == len(collects) and len(full) == len(tenth) == 3
    assert full[-1].config.episodes_per_task * 12 == 4080 and full[-1].config.prelude_tasks == 4
    for whole, part in zip(full, tenth):  # the same mix: clean, DART, chain preludes
        assert (whole.config.perturbation, whole.config.prelude_tasks) == (part.config.perturbation,
                                                                           part.config.prelude_tasks)
        assert 10 * part.config.episodes_per_task == whole.config.episodes_per_task
    for name in ("video", "vlm"):
        assert stages[name].config.preset == "cpu_minilm"
    # System 3 trains on the clean episodes only: the dataset grows after it.
    names = list(stages)
    assert names.index("clean1200") < names.index("video") < names.index("dart2400")
    # System 1 reads System 3 from `video` and System 2 from `vlm`, all stages on one feature cache setting.
    joint = stages["joint"].config
    assert joint.init == stages["video"].config.out + "/final"
    assert joint.policy.system2_from == stages["vlm"].config.out + "/final"
    assert {stage.config.features.stride for stage in recipe.stages if stage.kind == "train" and
            stage.config.stage == "policy"} == {6}
    # the tables compare the exported model with its arms, each arm trained on from the model's own System 1
    tables = stages["tables"].config.checkpoints
    assert tables["full"] == stages["follow_export"].config.out
    for role, arm in (("system1", "arm_s1"), ("system1_3", "arm_s13")):
        assert tables[role] == stages[arm + "_export"].config.out
        assert stages[arm].config.init == stages["follow"].config.out + "/final"
        assert not stages[arm].config.use_system2 and stages[arm].config.use_system3 == (role == "system1_3")
    assert tables["data10"] == stages["data10_export"].config.out
    evaluations = [stage for stage in recipe.stages if stage.kind == "evaluate"]
    assert evaluations and all(stage.config.out for stage in evaluations)  # each resumable (its journal)
    # every stage's settings pass their own checks now, not hours into the run (tables need their checkpoints)
    for stage in recipe.stages:
        if stage.kind == "train":
            stage.config.resolved().validate()
        elif stage.kind in ("collect", "evaluate"):
            stage.config.validate()
    recipe.workdir = str(tmp_path / "run")
    assert set(run_recipe(recipe, dry_run=True).values()) == {"pending"}
    assert "--preset cpu_minilm" in capsys.readouterr().out and not (tmp_path / "run").exists()
