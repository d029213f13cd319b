"""`trivla-drake tables`: the paper's tables from checkpoints, as Markdown, JSON and plots."""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

from trivla_drake.eval.paper_tables import TablesConfig
from trivla_drake.tasks.chain_benchmark import BENCHMARK_SHA256


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    from trivla_drake.nn import TriVLA, make_config, save_checkpoint

    root = tmp_path_factory.mktemp("ckpts")
    paths = {}
    for role, overrides in (("full", {}), ("system1", {"use_system2": False, "use_system3": False})):
        paths[role] = root / role
        save_checkpoint(TriVLA(make_config("tiny", **overrides), load_pretrained=False), str(paths[role]))
    return paths


def _tables(checkpoints, out, *extra):
    """`trivla-drake tables` in this process (a fresh interpreter would spend seconds importing)."""
    from trivla_drake.cli import main

    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(["tables", "--full", str(checkpoints["full"]), "--system1", str(checkpoints["system1"]),
                     "--out", str(out), "--set", "tasks=[turn_on_light]", "--episodes", "1", "--seeds", "0",
                     "--set", "chains=1", "--set", "latency_episodes=1", "--set", "max_steps=6",
                     "--set", "latency_tasks=[turn_on_light]", "--json", *extra])
    assert code == 0
    return json.loads(stdout.getvalue())


@pytest.fixture(scope="module")
def first_run(checkpoints, tmp_path_factory):
    out = tmp_path_factory.mktemp("tables")
    return out, _tables(checkpoints, out)


def test_tables_from_untrained_checkpoints(first_run, checkpoints):
    out, report = first_run
    assert report["main"]["tasks"]["turn_on_light"]["success_rate"] == 0.0  # untrained: no success
    assert [row["systems"] for row in report["ablation"]] == ["1", "1+2+3"]
    assert report["ablation"][0]["params_millions"] < report["ablation"][1]["params_millions"]
    assert set(report["latency"]) == {"latency off", "latency measured"}
    for name in ("report.md", "report.json", "per_task_success.png", "ablation.png", "tables_config.yaml"):
        assert (out / name).stat().st_size > 0, name
    assert "Sub-system ablation" in (out / "report.md").read_text()
    # The report keeps the config that made it: loaded back, it is the report's own, and the stage kind sees it done.
    from trivla_drake.config_io import load_config
    from trivla_drake.eval.stage_kinds import tables_is_done

    stored = load_config(TablesConfig, out / "tables_config.yaml")
    assert stored.checkpoints == {"full": str(checkpoints["full"]), "system1": str(checkpoints["system1"])}
    assert (stored.tasks, stored.chains, stored.max_steps) == (["turn_on_light"], 1, 6)
    assert tables_is_done(stored) and not tables_is_done(load_config(TablesConfig, out / "tables_config.yaml",
                                                                     ["chains=2"]))


def test_bad_roles_and_paths_are_named(tmp_path):
    with pytest.raises(ValueError, match="'full'"):
        TablesConfig(checkpoints={"system1": str(tmp_path)}).validate()
    with pytest.raises(ValueError, match="no config.json"):
        TablesConfig(checkpoints={"full": str(tmp_path)}).validate()
    with pytest.raises(ValueError, match="valid roles"):
        TablesConfig(checkpoints={"full": str(tmp_path), "half": str(tmp_path)}).validate()


def test_a_rerun_reuses_stored_evaluations_of_unchanged_checkpoints(checkpoints, first_run):
    out, first = first_run
    stored = sorted((out / "evaluations").glob("*.json"))
    # main, paraphrases, system1 at one seed; latency: 1 task x on/off
    assert len(stored) == 3 + 2
    # The Drake rows are keyed by the pipeline's stage offsets (rows from before it ran in order are redone).
    demo_settings = [json.loads(p.read_text())["settings"] for p in stored]
    assert sum(s.get("stage_offset_s") == 1e-4 and s.get("camera_frames") == "rendered_at_tick"
               for s in demo_settings if s["kind"] == "demo") == 2
    main = next(p for p in stored if json.loads(p.read_text())["settings"] == {
        "kind": "evaluate", "tasks": ["turn_on_light"], "episodes": 1, "seed": 0, "chains": 1,
        "paraphrases": False, "max_steps": 6, "chain_source": "benchmark", "benchmark_sha256": BENCHMARK_SHA256}
        and json.loads(p.read_text())["checkpoint"] == str(checkpoints["full"]))
    record = json.loads(main.read_text())
    record["result"]["tasks"]["turn_on_light"]["success_rate"] = 1.0  # marks the stored result
    main.write_text(json.dumps(record))
    second = _tables(checkpoints, out)
    assert first["main"]["tasks"]["turn_on_light"]["success_rate"] == 0.0
    assert second["main"]["tasks"]["turn_on_light"]["success_rate"] == 1.0  # reused, not recomputed
    assert sorted((out / "evaluations").glob("*.json")) == stored
    third = _tables(checkpoints, out, "--set", "reuse=false")
    assert third["main"]["tasks"]["turn_on_light"]["success_rate"] == 0.0
    elsewhere = out.parent / (out.name + "_elsewhere")
    fourth = _tables(checkpoints, elsewhere, "--set", f"results_dir={out / 'evaluations'}")
    assert fourth["main"]["tasks"]["turn_on_light"]["success_rate"] == 1.0  # another report's store, reused
    assert not (elsewhere / "evaluations").exists() and (elsewhere / "report.md").is_file()


def test_results_dir_without_reuse_is_refused(checkpoints, tmp_path, capsys):
    from trivla_drake.cli import main

    assert main(["tables", "--full", str(checkpoints["full"]), "--out", str(tmp_path / "t"),
                 "--set", f"results_dir={tmp_path / 'e'}", "--set", "reuse=false"]) == 2
    assert "results_dir names a folder of evaluations to reuse" in capsys.readouterr().err
    assert not (tmp_path / "t").exists()


def test_unknown_latency_task_is_named_before_any_work(checkpoints, tmp_path, capsys):
    from trivla_drake.cli import main

    assert main(["tables", "--full", str(checkpoints["full"]), "--out", str(tmp_path / "t"),
                 "--set", "latency_tasks=[lift_block, juggle]"]) == 2
    assert "unknown task 'juggle'" in capsys.readouterr().err
    assert not (tmp_path / "t").exists()


def test_the_10_percent_arm_gets_its_column_row_and_bars(tmp_path):
    """With a data10 checkpoint the report shows its per-task success beside the full model's, the data
    efficiency rows with their standard errors, and a third bar series in the per-task plot."""
    from trivla_drake.eval.paper_tables import format_tables, plot_tables

    def result(rate):
        return {"tasks": {"lift_block": {"success_rate": rate, "stderr": 0.1},
                          "open_drawer": {"success_rate": 1.0, "stderr": 0.0}},
                "average_success": (rate + 1.0) / 2, "average_stderr": 0.05}

    report = {"main": result(0.5), "paraphrases": result(0.0), "ablation": [], "data10": result(0.25),
              "data_efficiency": {"100%": 0.75, "10%": 0.625},
              "latency": {"latency off": {"success_rate": 1.0, "control_hz": 30.0}}}
    text = format_tables(report)
    assert "| task | success | held-out paraphrases | 10% of the demonstrations |" in text
    assert "| lift_block | 0.50 ± 0.10 | 0.00 ± 0.10 | 0.25 ± 0.10 |" in text
    assert "| 100% | 0.75 ± 0.05 |" in text and "| 10% | 0.62 ± 0.05 |" in text
    plot_tables(report, tmp_path)
    import matplotlib.image

    with_arm = matplotlib.image.imread(tmp_path / "per_task_success.png")
    del report["data10"], report["data_efficiency"]
    assert "10% of the demonstrations" not in format_tables(report)
    plot_tables(report, tmp_path)
    assert not np.array_equal(with_arm, matplotlib.image.imread(tmp_path / "per_task_success.png"))


def test_tables_run_every_evaluation_inside_one_rollout_runner(monkeypatch):
    """One local Ray for the whole command (each evaluation joins it), not one started and stopped per evaluation."""
    from trivla_drake.eval import paper_tables, rollout_runner

    state = {"open": 0, "entered": 0, "evaluations_outside": 0}

    class Runner:
        def __init__(self, workers, address):
            assert (workers, address) == (2, None)

        def __enter__(self):
            state["open"] += 1
            state["entered"] += 1

        def __exit__(self, *exc):
            state["open"] -= 1

    def over_seeds(config, checkpoint, **kwargs):
        state["evaluations_outside"] += state["open"] == 0
        return {"average_success": 0.5, "chain_avg_len": 1.0, "chain_avg_len_stderr": 0.1, "tasks": {}}

    monkeypatch.setattr(rollout_runner, "RolloutRunner", Runner)
    monkeypatch.setattr(paper_tables, "_over_seeds", over_seeds)
    def timed(name):  # model latency and the Drake latency rows are timed with no Ray workers alive beside them
        def figure(*args):
            state.setdefault("timed_inside", []).append((name, state["open"] > 0))
            return {"params_millions": 1.0, "latency_ms": 1.0} if name == "model" else {}
        return figure

    monkeypatch.setattr(paper_tables, "_model_figures", timed("model"))
    monkeypatch.setattr(paper_tables, "_latency_rows", timed("latency"))
    config = TablesConfig(checkpoints={"full": "a", "system1": "b", "data10": "c"}, workers=2)
    monkeypatch.setattr(TablesConfig, "validate", lambda self: None)
    report = paper_tables.make_tables(config)
    timed_inside = state.pop("timed_inside")
    assert state == {"open": 0, "entered": 1, "evaluations_outside": 0}
    assert timed_inside == [("model", False), ("model", False), ("latency", False)]
    assert [row["systems"] for row in report["ablation"]] and report["data_efficiency"]["10%"] == 0.5
