"""Bad command-line inputs that used to crash, mislead or delete data: each is refused with exit code 2 and one line
naming the flag, BEFORE any model loads or simulation runs (guards below fail the test if one starts), and nothing
already on disk is touched. Episode lists are drawn lazily, in the order they always had."""

from __future__ import annotations

import shutil
import tracemalloc
from pathlib import Path

import pytest

from trivla_drake.cli import main

SHIPPED = Path(__file__).resolve().parents[1] / "models" / "trivla_cpu"
HUGE = str(10**20)


def _must_not_run(*args, **kwargs):
    raise AssertionError("a model loaded or a simulation ran before the bad input was refused")


@pytest.fixture
def nothing_runs(monkeypatch):
    """Loading a model, exporting, building a station's run or a benchmark fails the test."""
    import trivla_drake.eval.diffik_benchmark as diffik_benchmark
    import trivla_drake.eval.evaluate as evaluate
    import trivla_drake.eval.model_loading as model_loading
    import trivla_drake.eval.scripted_run as scripted_run
    import trivla_drake.nn.checkpoint as checkpoint
    import trivla_drake.train.checkpoints as checkpoints
    import trivla_drake.train.model_soup as model_soup

    for module, name in ((model_loading, "load_model"), (checkpoint, "load_checkpoint"),
                         (checkpoints, "export_checkpoint"), (model_soup, "soup_checkpoints"),
                         (scripted_run, "run_scripted"), (diffik_benchmark, "benchmark_diffik"),
                         (evaluate, "_policy"), (evaluate, "run_jobs")):
        monkeypatch.setattr(module, name, _must_not_run)


def _refused(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


# ------------------------------------------------------------------ export / soup --out

def _user_folder(path: Path) -> dict[str, bytes]:
    path.mkdir(parents=True, exist_ok=True)
    (path / "thesis.tex").write_text("years of work")
    (path / "data").mkdir(exist_ok=True)
    (path / "data" / "runs.csv").write_text("1,2,3")
    return {str(p.relative_to(path)): p.read_bytes() for p in path.rglob("*") if p.is_file()}


def _files(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in path.rglob("*") if p.is_file()}


@pytest.mark.parametrize("command", ["export", "soup"])
def test_out_that_holds_other_things_is_refused_and_kept(command, tmp_path, capsys, nothing_runs):
    folder = tmp_path / "mine"
    before = _user_folder(folder)
    sources = [str(SHIPPED)] if command == "export" else [str(SHIPPED), str(SHIPPED)]
    err = _refused(capsys, [command, *sources, "--out", str(folder)])
    assert f"--out {folder} is not empty (data, thesis.tex)" in err
    assert "--overwrite" in err
    assert _files(folder) == before


@pytest.mark.parametrize("command", ["export", "soup"])
def test_out_never_replaces_the_working_folder_or_one_holding_it(command, tmp_path, capsys, monkeypatch, nothing_runs):
    work = tmp_path / "project" / "work"
    before = _user_folder(work)
    monkeypatch.chdir(work)
    sources = [str(SHIPPED)] if command == "export" else [str(SHIPPED), str(SHIPPED)]
    for out in (".", str(work), str(tmp_path / "project"), str(tmp_path)):
        err = _refused(capsys, [command, *sources, "--out", out, "--overwrite"])
        assert f"--out {out} is the working folder" in err
    assert _files(work) == before


def test_out_that_is_a_file_is_refused(tmp_path, capsys, nothing_runs):
    (tmp_path / "notes.txt").write_text("keep")
    assert "is a file, not a folder" in _refused(capsys, ["export", str(SHIPPED), "--out", str(tmp_path / "notes.txt")])
    assert (tmp_path / "notes.txt").read_text() == "keep"


def test_out_may_replace_an_earlier_export_an_empty_folder_or_anything_with_overwrite(tmp_path, capsys, monkeypatch):
    import trivla_drake.train.checkpoints as checkpoints

    written = []
    monkeypatch.setattr(checkpoints, "export_checkpoint", lambda source, out, **kwargs: written.append(out) or Path(out))
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    shutil.copy(SHIPPED / "config.json", earlier)
    (earlier / "model.safetensors").write_bytes(b"weights")
    (tmp_path / "empty").mkdir()
    mine = tmp_path / "mine"
    _user_folder(mine)
    for argv in ([str(earlier)], [str(tmp_path / "empty")], [str(tmp_path / "new")], [str(mine), "--overwrite"]):
        assert main(["export", str(SHIPPED), "--out", *argv]) == 0, capsys.readouterr().err
    assert written == [str(earlier), str(tmp_path / "empty"), str(tmp_path / "new"), str(mine)]
    (earlier / "notes.txt").write_text("mine")  # an export with a file of the user's is no longer just an export
    assert "is not empty" in _refused(capsys, ["export", str(SHIPPED), "--out", str(earlier)])


# ------------------------------------------------------------------ counts that cannot run

@pytest.mark.parametrize("argv, flag", [
    (["evaluate", "--episodes", HUGE], "--episodes"),
    (["evaluate", "--episodes", "0", "--chains", HUGE], "--chains"),
    (["collect", "--out", "{tmp}/data", "--episodes-per-task", HUGE], "--episodes-per-task"),
    (["demo", "--episodes", HUGE], "--episodes"),
    (["demo", "--chains", HUGE], "--chains"),
    (["tables", "--full", str(SHIPPED), "--out", "{tmp}/t", "--episodes", HUGE], "--episodes"),
    (["tables", "--full", str(SHIPPED), "--out", "{tmp}/t", "--set", f"latency_episodes={HUGE}"], "latency_episodes"),
])
def test_episode_counts_that_cannot_run_are_refused_naming_the_bound(argv, flag, tmp_path, capsys, nothing_runs):
    err = _refused(capsys, [a.replace("{tmp}", str(tmp_path)) for a in argv])
    assert f"{flag} must be at least" in err and "at most 100000 (an integer; MAX_EPISODES" in err
    assert not (tmp_path / "data").exists()  # collect wrote nothing


def test_evaluate_draws_its_episodes_as_they_run_in_the_order_they_always_had(monkeypatch):
    import trivla_drake.eval.evaluate as evaluate
    from trivla_drake.eval.evaluate import MAX_EPISODES, EvalConfig

    monkeypatch.setattr(evaluate, "_policy", lambda *args: None)
    ran = []
    result = {"task": "lift_block", "success": True, "seed": 0, "instruction": "", "reason": "", "completed": 0,
              "subtasks": []}
    monkeypatch.setattr(evaluate, "_run_job", lambda config, job: ran.append(job) or dict(result, task=job[1]))
    evaluate.evaluate(EvalConfig(tasks=["lift_block", "open_drawer"], episodes=2, chains=1, seed=7), progress=False)
    assert ran == [("episode", "lift_block", 0, 7), ("episode", "open_drawer", 0, 7), ("episode", "lift_block", 1, 7),
                   ("episode", "open_drawer", 1, 7), ("chain", "chain", 0, 7)]
    ran.clear()
    evaluate.evaluate(EvalConfig(tasks=["lift_block"], episodes=1, seeds=[7, 9]), progress=False)
    assert ran == [("episode", "lift_block", 0, 7), ("episode", "lift_block", 0, 9)]

    class Stop(Exception):
        pass

    def stop(config, job):
        raise Stop

    monkeypatch.setattr(evaluate, "_run_job", stop)
    tracemalloc.start()
    with pytest.raises(Stop):
        evaluate.evaluate(EvalConfig(tasks=["lift_block", "open_drawer"], episodes=MAX_EPISODES), progress=False)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 5e6  # a list of the 200000 jobs would take about 20 MB before the first one ran


def test_collect_draws_its_attempts_as_they_run_in_the_order_they_always_had():
    from trivla_drake.eval.collect import CollectConfig, _next_batch
    from trivla_drake.eval.evaluate import MAX_EPISODES

    config = CollectConfig(out="unused", episodes_per_task=3, tasks=["lift_block", "open_drawer", "push_block"])
    done = {"lift_block": {0, 2}, "open_drawer": set(), "push_block": {0, 1, 2}}
    failed = {"open_drawer": {"1": "timeout"}}
    assert list(_next_batch(config, done, failed)) == [("lift_block", 1), ("open_drawer", 0), ("open_drawer", 2),
                                                       ("open_drawer", 3)]
    config.episodes_per_task = MAX_EPISODES
    tracemalloc.start()
    batch = _next_batch(config, {task: set() for task in config.tasks}, {})
    assert [next(batch) for _ in range(4)] == [("lift_block", 0), ("open_drawer", 0), ("push_block", 0),
                                               ("lift_block", 1)]
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 1e6  # the listed batch would be 300000 attempts


# ------------------------------------------------------------------ demo, sim and bench flags

@pytest.mark.parametrize("argv, message", [
    (["demo", "--set", "max_seconds=-1"], "max_seconds must be a finite number of seconds above 0, got -1"),
    (["demo", "--set", "max_seconds=.nan"], "max_seconds must be a finite number of seconds above 0, got nan"),
    (["demo", "--set", "max_seconds=.inf"], "max_seconds must be a finite number of seconds above 0, got inf"),
    (["demo", "--seed", "4294967296"], "--seed must be an integer from 0 to 4294967295"),
    (["demo", "--seed", "-1"], "--seed must be an integer from 0 to 4294967295"),
    (["demo", "--instruction", ""], "--instruction is empty"),
    (["demo", "--instruction", "  "], "--instruction is empty"),
    (["demo", "--instruction", "pick up the \udcff block"], "--instruction is not UTF-8 text (\\udcff at character 12"),
    (["demo", "--set", "port=99999"], "port must be a port from 0 to 65535"),
    (["demo", "--set", "port=-1"], "port must be a port from 0 to 65535"),
    (["demo", "--record", "{tmp}"], "--record {tmp} is a folder: give a file name"),
    (["demo", "--record", "{tmp}/notes.txt/run.html"], "notes.txt is a file, not a folder"),
    (["demo", "--episodes", "0"], "--episodes must be at least 1"),
    (["sim", "--seconds", "inf"], "--seconds must be a finite number of seconds above 0, got inf"),
    (["sim", "--seconds", "nan"], "--seconds must be a finite number of seconds above 0, got nan"),
    (["sim", "--seconds", "0"], "--seconds must be a finite number of seconds above 0, got 0"),
    (["sim", "--set", "port=99999"], "port must be a port from 0 to 65535"),
    (["sim", "--record", "{tmp}"], "--record {tmp} is a folder: give a file name"),
    (["bench", "--set", "seconds=.inf"], "seconds must be a finite number of seconds above 0, got inf"),
    (["collect", "--out", "{tmp}/data", "--episodes-per-task", "1", "--set", "prelude_tasks=9"],
     "prelude_tasks must be an integer from 0 to 4"),
    (["evaluate", "--set", "inference.noise_scale=-1"], "inference.noise_scale must be a finite number >= 0"),
    (["evaluate", "--set", "episodes_per_task=1"], "EvalConfig has no field 'episodes_per_task'"),
])
def test_flags_are_refused_before_anything_runs(argv, message, tmp_path, capsys, nothing_runs):
    (tmp_path / "notes.txt").write_text("keep")
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    assert message.replace("{tmp}", str(tmp_path)) in _refused(capsys, argv)
    assert (tmp_path / "notes.txt").read_text() == "keep"


def test_port_zero_means_any_free_port_and_the_default_is_drakes():
    from trivla_drake.eval.setting_checks import check_port

    assert check_port(0) == 0 and check_port(None) is None and check_port(65535) == 65535


def test_a_scenario_with_an_unknown_contact_model_is_refused_before_simulating(tmp_path, capsys, nothing_runs):
    from trivla_drake.station.scenario import default_scenario_file

    bad = tmp_path / "typo.scenarios.yaml"
    bad.write_text(default_scenario_file().read_text().replace("hydroelastic_with_fallback", "hydroelastik"))
    err = _refused(capsys, ["sim", "--set", f"scenario={bad}"])
    assert (f"scenario 'default' in {bad}: plant_config.contact_model must be one of hydroelastic, point, "
            "hydroelastic_with_fallback; got 'hydroelastik'") in err


# ------------------------------------------------------------------ tables --seeds, train --seed

TABLES = ["tables", "--full", str(SHIPPED), "--out", "{tmp}/tables"]
TRAIN = ["train", "--stage", "policy", "--data", "{tmp}/data", "--out", "{tmp}/run"]


@pytest.mark.parametrize("argv, message", [
    ([*TABLES, "--seeds", "1000,x"], "--seeds must be base seeds as a range or a comma-separated list, e.g. "
                                     "1000-1017 or 1000,1001,1002; got '1000,x'"),
    ([*TABLES, "--seeds", "1000,,1001"], "--seeds must be base seeds as a range or a comma-separated list"),
    ([*TABLES, "--seeds", ""], "--seeds must be base seeds as a range or a comma-separated list"),
    ([*TABLES, "--seeds", "1005-1000"], "--seeds must be base seeds as a range or a comma-separated list"),
    (["evaluate", "--seeds", "1000-1002,x"], "--seeds must be base seeds as a range or a comma-separated list"),
    (["evaluate", "--seeds", "1000-1002", "--seed", "5"], "give --seed or --seeds, not both"),
    (["evaluate", "--seeds", "1000-1002,1001"], "--seeds must be distinct base seeds"),
    (["evaluate", "--seeds", "1000,4294967296"], "--seed must be an integer from 0 to 4294967295"),
    ([*TABLES, "--seeds", "1000,4294967296"], "--seeds must be an integer from 0 to 4294967295 (a 32-bit seed"),
    ([*TABLES, "--seeds=-1"], "--seeds must be an integer from 0 to 4294967295"),
    ([*TABLES, "--seeds", "1000,1001,1000"], "--seeds names [1000] more than once"),
    ([*TRAIN, "--seed=-1"], "seed must be an integer from 0 to 18446744073709551615 (what torch and numpy"),
    ([*TRAIN, "--seed", str(2**64)], "seed must be an integer from 0 to 18446744073709551615"),
])
def test_seeds_are_refused_before_anything_runs(argv, message, tmp_path, capsys, monkeypatch, nothing_runs):
    import trivla_drake.eval.policies as policies

    monkeypatch.setattr(policies, "load_policy", _must_not_run)
    err = _refused(capsys, [a.replace("{tmp}", str(tmp_path)) for a in argv])
    assert message in err
    assert list(tmp_path.iterdir()) == []  # no tables, run or evaluations folder written


def test_the_widest_seeds_are_taken():
    from trivla_drake.eval.paper_tables import TablesConfig
    from trivla_drake.train import TrainConfig

    TablesConfig(checkpoints={"full": str(SHIPPED)}, seeds=[0, 2**32 - 1]).validate()
    TrainConfig(stage="policy", data="d", out="o", seed=2**64 - 1).resolved().validate()
