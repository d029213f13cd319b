"""The shipped checkpoint (models/trivla_cpu): small enough to keep in git, loaded by default, and it
still solves a task it was trained on, in closed loop on a scene it never saw."""

import json
import logging
from pathlib import Path

import pytest

from trivla_drake.eval.model_loading import default_checkpoint_dir, load_model
from trivla_drake.systems.action_executor import ACTION_DIM

SIZE_LIMIT_BYTES = 25_000_000
# Episode 0 of evaluation seed 1000 (a scene no demonstration saw): solved in results/ (tables run), and
# never by the random baseline, so a damaged or untrained checkpoint fails here.
SOLVED_TASK, SOLVED_SEED = "unstack_block", 1000


def test_shipped_checkpoint_is_a_float16_cpu_checkpoint_under_25_mb():
    directory = default_checkpoint_dir()
    files = sorted(p.name for p in directory.iterdir())
    assert "model.safetensors" in files and "config.json" in files
    assert sum(p.stat().st_size for p in directory.rglob("*") if p.is_file()) <= SIZE_LIMIT_BYTES
    meta = json.loads((directory / "config.json").read_text())
    assert meta["preset"] == "cpu" and meta["weights_dtype"] == "float16"
    assert len(meta["action_space"]["names"]) == ACTION_DIM


def test_load_model_uses_the_shipped_checkpoint_without_warning(caplog):
    with caplog.at_level(logging.WARNING):
        model = load_model()
    assert "UNTRAINED" not in caplog.text
    assert model.config.preset == "cpu" and model.normalization is not None
    with caplog.at_level(logging.WARNING):
        load_model(preset="tiny")
    assert "UNTRAINED 'tiny'" in caplog.text


def test_shipped_checkpoint_solves_a_training_task_on_an_unseen_scene():
    import torch

    from trivla_drake.eval.evaluate import EvalConfig, evaluate

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as in the evaluations of results/ (one thread per worker)
    try:
        report = evaluate(EvalConfig(policy="trivla", tasks=[SOLVED_TASK], episodes=1, seed=SOLVED_SEED),
                          progress=False)
    finally:
        torch.set_num_threads(threads)
    assert report["tasks"][SOLVED_TASK]["success_rate"] == 1.0


def test_the_shipped_checkpoints_stored_tables_are_its_own(monkeypatch):
    """results/shipped_tables/report.md (the recipe's `tables` stage; results/report.md joins it with the soup's arms)
    must come from models/trivla_cpu: every evaluation it needs is found in results/evaluations/ under this
    checkpoint's contents (nothing is run), and gives its figures."""
    from trivla_drake.eval import paper_tables

    results = Path(__file__).resolve().parents[1] / "results"
    report = json.loads((results / "shipped_tables" / "report.json").read_text())
    settings = report["config"]
    config = paper_tables.TablesConfig(
        checkpoints={"full": str(default_checkpoint_dir())}, tasks=settings["tasks"], episodes=settings["episodes"],
        seeds=tuple(settings["seeds"]), chains=settings["chains"], max_steps=settings["max_steps"],
        chain_source=settings.get("chain_source", "drawn"),  # tables made before the fixed benchmark drew chains
        results_dir=str(results / "evaluations"))

    def not_stored(*args, **kwargs):
        raise AssertionError("an evaluation of the shipped tables is not stored for models/trivla_cpu")

    monkeypatch.setattr(paper_tables, "evaluate", not_stored)
    main = paper_tables._over_seeds(config, config.checkpoints["full"], chains=config.chains)
    paraphrases = paper_tables._over_seeds(config, config.checkpoints["full"], paraphrases=True)
    assert main["average_success"] == pytest.approx(report["main"]["average_success"])
    assert main["chain_avg_len"] == pytest.approx(report["main"]["chain_avg_len"])
    assert paraphrases["average_success"] == pytest.approx(report["paraphrases"]["average_success"])
