"""The recipe runner: a recipe is a YAML file of named stages, each a job (a registered stage kind) with its full
config; `run_recipe` runs them in order, skips those whose output is complete, resumes a killed one (its kind's
`run` resumes), and with `dry_run` prints the plan. A real recipe (recipes/trivla_cpu.yaml) looks like:

    name: trivla_cpu
    description: the shipped CPU model
    workdir: runs/trivla_cpu            # relative to the folder the runner is started in
    stages:
      - name: demos
        kind: collect
        config:
          out: ${workdir}/data/demos
          episodes_per_task: 50
          action_noise: 1.0
      - name: stage1
        kind: train
        after: [demos]
        config:
          stage: 1
          data: ${workdir}/data/demos
          out: ${workdir}/checkpoints/stage1
          preset: cpu

with each kind registered once by the code that owns its job, e.g.

    register_stage_kind("train", TrainConfig, run=lambda config, workdir: train(config),
                        is_done=lambda config, workdir: (Path(config.out) / "model.safetensors").is_file(),
                        describe=lambda config: f"trivla-drake train --config {config.out}/train.yaml")

`${workdir}` in any string of a stage's config is replaced by the recipe's workdir (made absolute), so one recipe
runs from any empty folder (write such a string in block style: inside `{...}` YAML reads its braces). The runner
keeps WORKDIR/configs/<stage>.yaml (each stage's config as it ran) and WORKDIR/recipe_state.json (which stages
were done, and when).
"""

# No `from __future__ import annotations` here: Recipe and Stage are read by Drake's typed YAML loader.
import dataclasses as dc
import datetime
import json
import os
import re
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, Optional

from trivla_drake.config_io import (
    ConfigError,
    apply_override,
    check_schema,
    merge_mapping,
    read_yaml_mapping,
    save_config,
)
from trivla_drake.data.durable import atomic_write_text

STATE_FILE = "recipe_state.json"
CONFIGS_DIR = "configs"
WORKDIR_VARIABLE = "${workdir}"


@dc.dataclass
class Stage:
    """One named job of a recipe."""

    # The stage's name (letters, digits, '_', '-'): unique in its recipe, and its config's file name.
    name: str = ""
    # The registered stage kind that runs it (collect, train, ...).
    kind: str = ""
    # Stages (defined earlier) whose output this one reads.
    after: list[str] = dc.field(default_factory=list)
    # The job's settings: an instance of its kind's schema (the YAML's `config:` mapping read through that schema).
    config: Any = None


@dc.dataclass
class Recipe:
    """A named list of stages and the folder they work in."""

    name: str = ""
    description: str = ""
    # The folder the stages write to (`${workdir}` in their configs); relative to where the runner starts.
    workdir: str = ""
    stages: list[Stage] = dc.field(default_factory=list)


@dc.dataclass(frozen=True)
class StageKind:
    """What the runner needs of a job: its config `schema`, `run(config, workdir)` (resuming a killed run),
    `is_done(config, workdir) -> bool` (its output is complete; reads only), and `describe(config) -> str` (the
    equivalent command, one line)."""

    kind: str
    schema: type
    run: Callable[[Any, str], Any]
    is_done: Callable[[Any, str], bool]
    describe: Callable[[Any], str]


class StageFailed(RuntimeError):
    """A stage whose job raised, or ended without completing its output; `stage` is its name."""

    def __init__(self, stage: str, message: str):
        super().__init__(message)
        self.stage = stage


_KINDS: dict[str, StageKind] = {}


def register_stage_kind(kind: str, schema: type, run: Callable, is_done: Callable, describe: Callable) -> None:
    """Makes `kind` usable in recipes (registering the same thing again is a no-op; another thing under a taken
    name is a ValueError)."""
    check_schema(schema)
    entry = StageKind(kind, schema, run, is_done, describe)
    if _KINDS.get(kind, entry) != entry:
        raise ValueError(f"stage kind {kind!r} is already registered (schema {_KINDS[kind].schema.__name__})")
    _KINDS[kind] = entry


def registered_stage_kinds() -> list[str]:
    """The names of the registered stage kinds, sorted."""
    return sorted(_KINDS)


def load_recipe(path: os.PathLike, overrides: Iterable[str] = ()) -> Recipe:
    """The recipe in the YAML file at `path`, each stage's config read through its kind's schema, then the
    overrides "workdir=DIR" (a recipe field) or "<stage>.<dotted.field>=value" (a stage's config) in order.
    ConfigError naming the file, the stage and the field."""
    where = f"recipe {os.fspath(path)}"
    document = read_yaml_mapping(path)
    stage_mappings = document.pop("stages", None) or []
    if not isinstance(stage_mappings, list):
        raise ConfigError(f"{where}: stages must be a list of stages, got {stage_mappings!r}")
    recipe = merge_mapping(Recipe(), document, where=where)
    for index, mapping in enumerate(stage_mappings):
        if not isinstance(mapping, dict):
            raise ConfigError(f"{where}: stages[{index}] must be a mapping (name, kind, after, config)")
        mapping = dict(mapping)
        config = mapping.pop("config", None) or {}
        stage = merge_mapping(Stage(), mapping, where=f"{where}: stages[{index}]")
        label = f"{where}: stage {stage.name or index!r}"
        if not stage.kind:
            raise ConfigError(f"{label}: kind is missing ({_known_kinds()})")
        stage.config = merge_mapping(_kind_of(stage, label).schema(), config, where=f"{label}: config")
        recipe.stages.append(stage)
    for override in overrides:
        recipe = _apply_recipe_override(recipe, override)
    check_recipe(recipe, where=where)
    return recipe


def check_recipe(recipe: Recipe, *, where: str = "recipe") -> None:
    """ConfigError for a recipe the runner cannot run: no workdir, a stage without a usable name, an unknown kind
    (naming the registered ones), a config not of its kind's schema, a repeated name, `after` naming a stage that
    is not defined before it."""
    if not recipe.workdir:
        raise ConfigError(f"{where}: workdir is missing (the folder the stages write to)")
    earlier = []
    for stage in recipe.stages:
        label = f"{where}: stage {stage.name!r}"
        if not re.fullmatch(r"[A-Za-z0-9_-]+", stage.name):
            raise ConfigError(f"{label}: name must be letters, digits, '_' or '-' (it names the stage's files)")
        if stage.name in earlier:
            raise ConfigError(f"{label}: name is used by an earlier stage; stage names must be unique")
        kind = _kind_of(stage, label)
        if not isinstance(stage.config, kind.schema):
            raise ConfigError(f"{label}: config is a {type(stage.config).__name__}, not the {kind.schema.__name__} "
                              f"of kind {stage.kind!r}")
        for needed in stage.after:
            if needed not in earlier:
                raise ConfigError(f"{label}: after names {needed!r}, which is not a stage defined before it "
                                  f"(earlier: {', '.join(earlier) or 'none'})")
        earlier.append(stage.name)


def run_recipe(recipe: Recipe, *, dry_run: bool = False, only: Optional[Iterable[str]] = None,
               from_stage: Optional[str] = None, progress: bool = True) -> dict[str, str]:
    """Runs the recipe's stages in order (all, or those named in `only`, or those from `from_stage` on): a stage
    whose output is complete is skipped, the others run, the first failure stops the run (StageFailed naming it).
    With `dry_run`, prints the plan (name, kind, done/pending, command) and runs nothing. Returns each selected
    stage's status: "done" (already), "ran", or "pending" (dry run)."""
    check_recipe(recipe, where=f"recipe {recipe.name}")
    workdir = os.path.abspath(os.path.expanduser(recipe.workdir))
    stages = [dc.replace(stage, config=expand_workdir(stage.config, workdir))
              for stage in _selected(recipe, only, from_stage)]
    done = {stage.name: _call(stage, "is_done", stage.config, workdir) for stage in stages}
    _check_needs_met(recipe, stages, done, workdir)
    if dry_run:
        print(_plan(recipe, stages, done, workdir), flush=True)
        return {name: "done" if is_done else "pending" for name, is_done in done.items()}
    state = _read_state(workdir, recipe)
    statuses = {}
    for stage in stages:
        entry = state["stages"].setdefault(stage.name, {})
        if done[stage.name]:
            _say(progress, recipe, stage, "done, skipped")
            if entry.get("status") != "done":
                entry.update(kind=stage.kind, status="done", finished=_now())
                _write_state(workdir, state)
            statuses[stage.name] = "done"
            continue
        _run_stage(recipe, stage, workdir, state, progress)
        statuses[stage.name] = "ran"
    return statuses


def expand_workdir(config, workdir: str):
    """A copy of `config` (a dataclass, list, dict or string, nested) with `${workdir}` in its strings replaced."""
    if isinstance(config, str):
        return config.replace(WORKDIR_VARIABLE, workdir)
    if isinstance(config, list):
        return [expand_workdir(item, workdir) for item in config]
    if isinstance(config, dict):
        return {key: expand_workdir(value, workdir) for key, value in config.items()}
    if dc.is_dataclass(config) and not isinstance(config, type):
        return dc.replace(config, **{field.name: expand_workdir(getattr(config, field.name), workdir)
                                     for field in dc.fields(config) if field.init})
    return config


def _run_stage(recipe: Recipe, stage: Stage, workdir: str, state: dict, progress: bool) -> None:
    """Saves the stage's config, runs it and checks its output, recording it in the state file before and after."""
    entry = state["stages"][stage.name]
    config_file = Path(workdir) / CONFIGS_DIR / f"{stage.name}.yaml"
    save_config(stage.config, config_file)
    entry.clear()
    entry.update(kind=stage.kind, status="running", started=_now(), config=f"{CONFIGS_DIR}/{config_file.name}")
    _write_state(workdir, state)
    _say(progress, recipe, stage, f"running: {_call(stage, 'describe', stage.config)}")
    start = time.monotonic()
    try:
        _call(stage, "run", stage.config, workdir)
        if not _call(stage, "is_done", stage.config, workdir):
            raise StageFailed(stage.name, f"stage {stage.name!r} ({stage.kind}) ran to its end but its output is "
                                          "not complete (is_done is false)")
    except StageFailed as failure:
        entry.update(status="failed", finished=_now(), error=str(failure))
        _write_state(workdir, state)
        raise
    entry.update(status="done", finished=_now())
    _write_state(workdir, state)
    _say(progress, recipe, stage, f"done in {time.monotonic() - start:.1f} s")


def _kind_of(stage: Stage, label: str) -> StageKind:
    """The registered kind of `stage`; ConfigError listing the registered ones."""
    if stage.kind not in _KINDS:
        raise ConfigError(f"{label}: unknown kind {stage.kind!r} ({_known_kinds()})")
    return _KINDS[stage.kind]


def _known_kinds() -> str:
    return f"registered kinds: {', '.join(registered_stage_kinds())}" if _KINDS else "no stage kinds are registered"


def _apply_recipe_override(recipe: Recipe, override: str) -> Recipe:
    """One override of load_recipe: "name|description|workdir=value", or "<stage>.<field>=value" into that stage's
    config."""
    if override.partition("=")[0].strip() in ("name", "description", "workdir"):
        return apply_override(recipe, override)
    head, _, rest = override.partition(".")
    stage = next((stage for stage in recipe.stages if stage.name == head), None)
    if stage is None:
        raise ConfigError(f"--set {override}: {head!r} is neither a recipe field (name, description, workdir) nor a "
                          f"stage (stages: {', '.join(stage.name for stage in recipe.stages) or 'none'})")
    stage.config = apply_override(stage.config, rest, where=f"--set {override}")
    return recipe


def _selected(recipe: Recipe, only: Optional[Iterable[str]], from_stage: Optional[str]) -> list[Stage]:
    """The stages `only` and `from_stage` pick, in recipe order; ValueError naming an unknown stage."""
    names = [stage.name for stage in recipe.stages]
    only = [only] if isinstance(only, str) else None if only is None else list(only)
    for given in (only or []) + ([from_stage] if from_stage is not None else []):
        if given not in names:
            raise ValueError(f"recipe {recipe.name!r} has no stage {given!r} (stages: {', '.join(names)})")
    first = 0 if from_stage is None else names.index(from_stage)
    return [stage for stage in recipe.stages[first:] if only is None or stage.name in only]


def _check_needs_met(recipe: Recipe, stages: list[Stage], done: dict[str, bool], workdir: str) -> None:
    """ValueError when a selected stage reads a stage that is neither selected nor done."""
    by_name = {stage.name: stage for stage in recipe.stages}
    for stage in stages:
        for needed in stage.after:
            if needed in done:
                continue
            other = dc.replace(by_name[needed], config=expand_workdir(by_name[needed].config, workdir))
            if not _call(other, "is_done", other.config, workdir):
                raise ValueError(f"stage {stage.name!r} needs stage {needed!r}, which is not done and not selected: "
                                 "run it first (or select it too)")


def _call(stage: Stage, what: str, *args):
    """`what` (run, is_done, describe) of the stage's kind; StageFailed naming the stage when it raises."""
    try:
        return getattr(_KINDS[stage.kind], what)(*args)
    except Exception as error:
        raise StageFailed(stage.name, f"stage {stage.name!r} ({stage.kind}) failed in {what}: "
                                      f"{type(error).__name__}: {error}") from error


def _say(progress: bool, recipe: Recipe, stage: Stage, message: str) -> None:
    if progress:
        print(f"[{recipe.name}] stage {stage.name} ({stage.kind}): {message}", flush=True)


def _plan(recipe: Recipe, stages: list[Stage], done: dict[str, bool], workdir: str) -> str:
    """The dry run's table: one line per stage, name, kind, done/pending and the equivalent command."""
    name_width = max((len(stage.name) for stage in stages), default=0)
    kind_width = max((len(stage.kind) for stage in stages), default=0)
    lines = [f"recipe {recipe.name}: {recipe.description}".rstrip(": "), f"workdir {workdir}"]
    for stage in stages:
        status = "done" if done[stage.name] else "pending"
        lines.append(f"  {stage.name:<{name_width}}  {stage.kind:<{kind_width}}  {status:<7}  "
                     f"{_call(stage, 'describe', stage.config)}")
    return "\n".join(lines)


def _read_state(workdir: str, recipe: Recipe) -> dict:
    """The state file's record (a fresh one when missing or unreadable: the stages' outputs are the truth)."""
    try:
        state = json.loads((Path(workdir) / STATE_FILE).read_text())
        if isinstance(state, dict) and isinstance(state.get("stages"), dict):
            return state
    except (OSError, ValueError):
        pass
    return {"recipe": recipe.name, "stages": {}}


def _write_state(workdir: str, state: dict) -> None:
    atomic_write_text(Path(workdir) / STATE_FILE, json.dumps(state, indent=2) + "\n")


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
