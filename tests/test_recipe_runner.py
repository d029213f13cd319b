"""The recipe runner with toy stage kinds: skip done, resume killed, stop at a failure, dry run, errors that name the
stage and the field, the state file, ${workdir}, only / from_stage."""

# No `from __future__ import annotations`: the toy configs below are read by Drake's typed YAML loader.
import dataclasses as dc
import json
from pathlib import Path
from typing import Optional

import pytest

from trivla_drake.config_io import ConfigError, load_config
from trivla_drake.recipe import (
    StageFailed,
    load_recipe,
    register_stage_kind,
    registered_stage_kinds,
    run_recipe,
)

CALLS: list[str] = []  # "kind:out" of every run() call


@dc.dataclass
class WriteConfig:
    out: str = ""
    text: str = "hello"
    write: bool = True  # False: the job "ends" without writing its output


def run_write(config: WriteConfig, workdir: str) -> None:
    CALLS.append(f"toy_write:{config.out}")
    if config.write:
        Path(config.out).parent.mkdir(parents=True, exist_ok=True)
        Path(config.out).write_text(config.text)


@dc.dataclass
class FailConfig:
    message: str = "boom"


def run_fail(config: FailConfig, workdir: str) -> None:
    CALLS.append("toy_fail")
    raise RuntimeError(config.message)


class Killed(BaseException):
    """Stands for the process being killed (not an Exception: the runner cannot catch it)."""


@dc.dataclass
class PartsConfig:
    out_dir: str = ""
    parts: int = 3
    kill_after: Optional[int] = None  # parts written by this call before it is "killed"


def run_parts(config: PartsConfig, workdir: str) -> None:
    """Writes part_<i>.txt for each missing part: a killed run resumes where it stopped."""
    written = 0
    for index in range(config.parts):
        part = Path(config.out_dir) / f"part_{index}.txt"
        if part.exists():
            continue
        if config.kill_after is not None and written == config.kill_after:
            raise Killed()
        part.parent.mkdir(parents=True, exist_ok=True)
        part.write_text(str(index))
        CALLS.append(f"toy_parts:{index}")
        written += 1


def parts_done(config: PartsConfig, workdir: str) -> bool:
    return all((Path(config.out_dir) / f"part_{index}.txt").exists() for index in range(config.parts))


register_stage_kind("toy_write", WriteConfig, run_write, lambda config, workdir: Path(config.out).is_file(),
                    lambda config: f"toy write {config.out}")
register_stage_kind("toy_fail", FailConfig, run_fail, lambda config, workdir: False, lambda config: "toy fail")
register_stage_kind("toy_parts", PartsConfig, run_parts, parts_done, lambda config: f"toy parts {config.out_dir}")


@pytest.fixture(autouse=True)
def _fresh_calls():
    CALLS.clear()


THREE = """\
name: toy
description: three toy stages
workdir: {workdir}
stages:
  - name: a
    kind: toy_write
    config:
      out: ${{workdir}}/a.txt
  - name: b
    kind: toy_write
    after: [a]
    config:
      out: ${{workdir}}/sub/b.txt
      text: bee
  - name: c
    kind: toy_write
    config:
      out: ${{workdir}}/c.txt
"""


def recipe_file(tmp_path, text, workdir="work", name="recipe.yaml"):
    path = tmp_path / name
    path.write_text(text.format(workdir=workdir))
    return path


def test_runs_in_order_saves_configs_and_skips_done_stages(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # the workdir "work" is relative to where the runner starts
    recipe = load_recipe(recipe_file(tmp_path, THREE))
    assert run_recipe(recipe) == {"a": "ran", "b": "ran", "c": "ran"}
    work = tmp_path / "work"
    assert CALLS == [f"toy_write:{work}/a.txt", f"toy_write:{work}/sub/b.txt", f"toy_write:{work}/c.txt"]
    assert (work / "sub" / "b.txt").read_text() == "bee"
    assert load_config(WriteConfig, work / "configs" / "b.yaml") == WriteConfig(out=f"{work}/sub/b.txt", text="bee")
    state = json.loads((work / "recipe_state.json").read_text())
    assert [state["stages"][name]["status"] for name in "abc"] == ["done"] * 3
    assert state["stages"]["b"]["config"] == "configs/b.yaml" and state["stages"]["b"]["finished"]

    CALLS.clear()
    (work / "c.txt").unlink()
    assert run_recipe(recipe) == {"a": "done", "b": "done", "c": "ran"}
    assert CALLS == [f"toy_write:{work}/c.txt"]
    assert "stage a (toy_write): done, skipped" in capsys.readouterr().out


def test_a_killed_stage_is_resumed(tmp_path):
    path = recipe_file(tmp_path, """\
name: toy
workdir: {workdir}
stages:
  - name: parts
    kind: toy_parts
    config:
      out_dir: ${{workdir}}/parts
      kill_after: 1
""", workdir=tmp_path / "work")
    with pytest.raises(Killed):
        run_recipe(load_recipe(path), progress=False)
    assert CALLS == ["toy_parts:0"]
    state = json.loads((tmp_path / "work" / "recipe_state.json").read_text())
    assert state["stages"]["parts"]["status"] == "running"
    assert run_recipe(load_recipe(path, ["parts.kill_after=null"]), progress=False) == {"parts": "ran"}
    assert CALLS == ["toy_parts:0", "toy_parts:1", "toy_parts:2"]


def test_the_first_failure_stops_the_run_naming_the_stage(tmp_path):
    path = recipe_file(tmp_path, """\
name: toy
workdir: {workdir}
stages:
  - name: a
    kind: toy_write
    config: {{out: {workdir}/a.txt}}
  - name: bad
    kind: toy_fail
    config: {{message: disk full}}
  - name: c
    kind: toy_write
    config: {{out: {workdir}/c.txt}}
""", workdir=tmp_path / "work")
    with pytest.raises(StageFailed, match=r"stage 'bad' \(toy_fail\) failed in run: RuntimeError: disk full") \
            as caught:
        run_recipe(load_recipe(path), progress=False)
    assert caught.value.stage == "bad"
    assert CALLS == [f"toy_write:{tmp_path}/work/a.txt", "toy_fail"]
    state = json.loads((tmp_path / "work" / "recipe_state.json").read_text())
    assert state["stages"]["a"]["status"] == "done"
    assert state["stages"]["bad"]["status"] == "failed" and "disk full" in state["stages"]["bad"]["error"]
    assert "c" not in state["stages"]


def test_a_stage_that_ends_without_its_output_fails(tmp_path):
    path = recipe_file(tmp_path, THREE, workdir=tmp_path / "work")
    with pytest.raises(StageFailed, match="stage 'a' .* output is not complete"):
        run_recipe(load_recipe(path, ["a.write=false"]), progress=False)


def test_dry_run_prints_the_plan_and_runs_nothing(tmp_path, capsys):
    work = tmp_path / "work"
    recipe = load_recipe(recipe_file(tmp_path, THREE, workdir=work))
    (tmp_path / "c.txt").write_text("")
    recipe.stages[2].config.out = str(tmp_path / "c.txt")  # c's output is already there
    assert run_recipe(recipe, dry_run=True) == {"a": "pending", "b": "pending", "c": "done"}
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "recipe toy: three toy stages"
    assert lines[2].split() == ["a", "toy_write", "pending", "toy", "write", f"{work}/a.txt"]
    assert lines[3].split() == ["b", "toy_write", "pending", "toy", "write", f"{work}/sub/b.txt"]
    assert lines[4].split()[:3] == ["c", "toy_write", "done"]
    assert CALLS == [] and not work.exists()


@pytest.mark.parametrize("stages, words", [
    ("  - {name: a, kind: toy_write, config: {outt: x}}\n", ["stage 'a'", "WriteConfig has no field 'outt'"]),
    ("  - {name: a, kind: toy_write, config: {write: maybe}}\n", ["stage 'a'", "config: write", "WriteConfig.write"]),
    ("  - {name: a, kind: toy_writ}\n", ["stage 'a'", "unknown kind 'toy_writ'", "toy_fail, toy_parts, toy_write"]),
    ("  - {name: a}\n", ["stage 'a'", "kind is missing"]),
    ("  - {name: a, kind: toy_fail, afterr: []}\n", ["stages[0]", "Stage has no field 'afterr'"]),
    ("  - {name: a, kind: toy_fail}\n  - {name: a, kind: toy_fail}\n", ["stage 'a'", "earlier stage"]),
    ("  - {name: a, kind: toy_fail, after: [b]}\n  - {name: b, kind: toy_fail}\n",
     ["stage 'a'", "after names 'b'", "not a stage defined before it"]),
    ("  - {name: a b, kind: toy_fail}\n", ["stage 'a b'", "name must be"]),
])
def test_recipe_errors_name_the_stage_and_field(tmp_path, stages, words):
    path = tmp_path / "recipe.yaml"
    path.write_text(f"name: toy\nworkdir: work\nstages:\n{stages}")
    with pytest.raises(ConfigError) as caught:
        load_recipe(path)
    assert str(path) in str(caught.value)
    for word in words:
        assert word in str(caught.value)


def test_recipe_level_errors(tmp_path):
    path = tmp_path / "recipe.yaml"
    path.write_text("name: toy\nstages: []\n")
    with pytest.raises(ConfigError, match="workdir is missing"):
        load_recipe(path)
    path.write_text("name: toy\nworkdirr: w\n")
    with pytest.raises(ConfigError, match="Recipe has no field 'workdirr'"):
        load_recipe(path)
    path.write_text(THREE.format(workdir="w"))
    with pytest.raises(ConfigError, match=r"--set a.outt=1: WriteConfig has no field 'outt'"):
        load_recipe(path, ["a.outt=1"])
    with pytest.raises(ConfigError, match=r"'zz' is neither a recipe field .* \(stages: a, b, c\)"):
        load_recipe(path, ["zz.out=1"])
    assert load_recipe(path, ["workdir=elsewhere"]).workdir == "elsewhere"


def test_state_file_is_written_atomically_after_each_stage(tmp_path, monkeypatch):
    import trivla_drake.recipe as recipe_module

    writes = []
    real_write = recipe_module.atomic_write_text
    monkeypatch.setattr(recipe_module, "atomic_write_text",
                        lambda path, text: (writes.append(json.loads(text)), real_write(path, text)))
    seen_during_b = []
    work = tmp_path / "work"

    def run_and_read_state(config, workdir):
        seen_during_b.append(json.loads((work / "recipe_state.json").read_text()))
        run_write(config, workdir)

    recipe = load_recipe(recipe_file(tmp_path, THREE, workdir=work))
    register_stage_kind("toy_write_spy", WriteConfig, run_and_read_state,
                        lambda config, workdir: Path(config.out).is_file(), lambda config: "spy")
    recipe.stages[1].kind = "toy_write_spy"
    run_recipe(recipe, progress=False)
    assert [write["stages"][name]["status"] for write, name in zip(writes, "aabbcc")] == ["running", "done"] * 3
    assert seen_during_b[0]["stages"]["a"]["status"] == "done"
    assert seen_during_b[0]["stages"]["b"]["status"] == "running"
    assert sorted(path.name for path in work.iterdir()) == ["a.txt", "c.txt", "configs", "recipe_state.json", "sub"]


def test_only_and_from_stage(tmp_path):
    work = tmp_path / "work"
    recipe = load_recipe(recipe_file(tmp_path, THREE, workdir=work))
    assert run_recipe(recipe, only=["c"], progress=False) == {"c": "ran"}
    with pytest.raises(ValueError, match="stage 'b' needs stage 'a', which is not done"):
        run_recipe(recipe, from_stage="b", progress=False)
    assert run_recipe(recipe, only="a", progress=False) == {"a": "ran"}
    assert run_recipe(recipe, from_stage="b", progress=False) == {"b": "ran", "c": "done"}
    with pytest.raises(ValueError, match="no stage 'd' \\(stages: a, b, c\\)"):
        run_recipe(recipe, only=["d"], progress=False)


def test_registry_refuses_a_second_kind_under_a_taken_name():
    with pytest.raises(ValueError, match="'toy_write' is already registered"):
        register_stage_kind("toy_write", FailConfig, run_fail, lambda config, workdir: False, lambda config: "x")
    assert {"toy_write", "toy_fail", "toy_parts"} <= set(registered_stage_kinds())
