"""The project's one config mechanism: a job's settings are a typed (nested) dataclass, read from a YAML file and
then from `--set dotted.field=value` overrides with Drake's typed YAML loader, and written back as YAML.

    config = load_config(TrainConfig, "train.yaml", ["lr=1e-4", "steps=2000"])
    save_config(config, "runs/x/train.yaml")   # "# trivla_drake.train.config.TrainConfig" then the fields

Why Drake's `yaml_load_typed`: the scenario and TriVLAPolicyConfig already use it, it merges into defaults field by
field, and it reads Drake's own config types (MultibodyPlantConfig, Transform, ...) as fields. Its limits, which a
schema must respect: no `from __future__ import annotations` in the schema's module, no frozen dataclasses, lists
rather than tuples, `typing.Optional` for a field that may be null. Drake is imported only when a file or an
override is read or a config written, so a config of defaults works where Drake is not installed.
"""

# No `from __future__ import annotations` here: the schemas' field types are read at run time.
import argparse
import copy
import dataclasses as dc
import difflib
import json
import os
import re
import shlex
import typing
from collections.abc import Iterable, Mapping
from typing import Any, Optional

import yaml

from trivla_drake.data.durable import atomic_write_text


class ConfigError(ValueError):
    """A config file, mapping or override that does not fit its schema; the message names where and the field."""


def load_config(schema: type, path: Optional[os.PathLike] = None, overrides: Iterable[str] = (), *, defaults=None):
    """An instance of the dataclass `schema`: `defaults` (else the schema's own defaults), merged with the YAML file at
    `path` (if given), then with each "dotted.field=value" override in order (value read as YAML: 3, 1e-4, true,
    [a, b], null). ConfigError naming the file or the override and the field."""
    check_schema(schema)
    config = schema() if defaults is None else copy.deepcopy(defaults)
    if not isinstance(config, schema):
        raise TypeError(f"load_config: defaults is a {type(config).__name__}, not a {schema.__name__}")
    if path is not None:
        config = merge_mapping(config, read_yaml_mapping(path), where=f"config file {os.fspath(path)}")
    for override in overrides:
        config = apply_override(config, override)
    return config


def check_schema(schema: type) -> None:
    """TypeError unless `schema` is a dataclass Drake's typed YAML loader can read (nested dataclasses too)."""
    if not (isinstance(schema, type) and dc.is_dataclass(schema)):
        raise TypeError(f"a config schema must be a dataclass type, got {schema!r}")
    if schema.__dataclass_params__.frozen:
        raise TypeError(f"config schema {schema.__name__} is frozen: Drake's YAML loader sets fields, drop frozen=True")
    for field in dc.fields(schema):
        if isinstance(field.type, str):
            raise TypeError(f"config schema {schema.__name__}.{field.name} has the string annotation {field.type!r}: "
                            f"drop `from __future__ import annotations` from {schema.__module__}")
        if isinstance(field.type, type) and dc.is_dataclass(field.type):
            check_schema(field.type)


def read_yaml_mapping(path: os.PathLike) -> dict:
    """The YAML mapping in the file at `path` ({} for an empty file); ConfigError naming the file otherwise."""
    if not os.path.isfile(path):
        raise ConfigError(f"config file {os.fspath(path)} does not exist")
    try:
        data = _drake_yaml().yaml_load_file(os.fspath(path))
    except yaml.YAMLError as error:
        raise ConfigError(f"config file {os.fspath(path)} is not valid YAML: {error}") from None
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"config file {os.fspath(path)} must hold a mapping of field: value, "
                          f"not a {type(data).__name__}")
    return dict(data)


def merge_mapping(config, mapping: Mapping, *, where: str):
    """A copy of the dataclass `config` with the fields of the (untyped, YAML-like) `mapping` merged in; ConfigError
    "`where`: dotted.field: what is wrong" when one does not fit."""
    try:
        return _merge_checked(config, mapping)
    except _Misfit as misfit:
        raise ConfigError(f"{where}: {misfit.field}: {misfit.problem}") from None


def apply_override(config, override: str, *, where: Optional[str] = None):
    """`config` with one "dotted.field=value" override merged in; a value that YAML reads as a number or boolean
    but the field wants as a string is taken as the string (--set name=2024). Errors start with `where` (default
    "--set <override>")."""
    where = f"--set {override}" if where is None else where
    key, equals, text = override.partition("=")
    key = key.strip()
    if not equals or not key:
        raise ConfigError(f"{where}: an override is dotted.field=value, e.g. --set train.lr=1e-4")
    try:
        value = _drake_yaml().yaml_load_data(text) if text.strip() else None
    except yaml.YAMLError as error:
        raise ConfigError(f"{where}: the value is not valid YAML: {error}") from None
    readings = [value] + ([text] if isinstance(value, (bool, int, float)) else [])
    misfits = []
    for reading in readings:
        try:
            return _merge_checked(config, _nested(key, reading))
        except _Misfit as misfit:
            misfits.append(misfit)
    raise ConfigError(f"{where}: {misfits[0].problem}")  # the override names the field already


def dump_config(config) -> str:
    """`config` as YAML: a comment naming its schema, then every field (defaults included). Where Drake is not
    installed (a training machine may lack it) PyYAML writes the same fields, which `load_config` and the training
    checkpoints' reader read alike."""
    schema = type(config)
    try:
        text = _drake_yaml().yaml_dump_typed(config)
    except ModuleNotFoundError:
        text = yaml.safe_dump(dc.asdict(config), sort_keys=False)
    except Exception as error:  # e.g. a tuple field: NotImplementedError
        raise ConfigError(f"cannot write {schema.__name__} as YAML: {error}") from None
    return f"# {schema.__module__}.{schema.__qualname__}\n{text}"


def save_config(config, path: os.PathLike) -> None:
    """Writes `dump_config(config)` to `path` atomically (nothing is written when it cannot be dumped)."""
    atomic_write_text(path, dump_config(config))


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """Adds `--config FILE` and repeatable `--set KEY=VALUE` to `parser` (read them with config_from_args)."""
    parser.add_argument("--config", metavar="FILE", default=None,
                        help="YAML file of settings (fields of the job's config; the rest keep their defaults)")
    parser.add_argument("--set", dest="overrides", metavar="KEY=VALUE", action="append", default=[],
                        help="override one setting after --config, e.g. --set train.lr=1e-4 (repeatable, in order)")
    parser.add_argument("--print-config", action="store_true",
                        help="print the full config this command would run with (YAML, loadable by --config) and exit")


def with_flags(config, flags: Mapping[str, Any]):
    """`config` with each dotted field of `flags` whose value is not None set to it (the command line's few direct
    flags, applied after --config and --set); a copy, `config` is left as it is."""
    config = copy.deepcopy(config)
    for dotted, value in flags.items():
        if value is None:
            continue
        *parents, name = dotted.split(".")
        target = config
        for parent in parents:
            target = getattr(target, parent)
        if not hasattr(target, name):
            raise ConfigError(f"{type(target).__name__} has no field {name!r} (flag for {dotted})")
        setattr(target, name, value)
    return config


def config_from_args(schema: type, args: argparse.Namespace, *, defaults=None):
    """The `schema` config given by the `--config` and `--set` arguments of add_config_arguments."""
    return load_config(schema, args.config, args.overrides, defaults=defaults)


def leaf_fields(config) -> dict[str, Any]:
    """The dataclass `config`'s fields as {dotted name: value}, nested dataclasses flattened (lists and dicts whole,
    dataclasses inside them as dicts)."""
    leaves: dict[str, Any] = {}
    for field in dc.fields(config):
        value = getattr(config, field.name)
        if dc.is_dataclass(value):
            leaves.update({f"{field.name}.{name}": inner for name, inner in leaf_fields(value).items()})
        else:
            leaves[field.name] = [dc.asdict(item) if dc.is_dataclass(item) else item for item in value] \
                if isinstance(value, list) else value
    return leaves


def flag_words(flag: str, value: Any) -> list[str]:
    """The command-line words setting a field to `value` with its `flag`: for a boolean the bare flag where it is true
    (a `--no-...` flag: where it is false), a comma-separated list, else the flag and the value."""
    if isinstance(value, bool):
        return [flag] if value != flag.startswith("--no-") else []
    if isinstance(value, list):
        return [flag, ",".join(str(item) for item in value)]
    return [flag, str(value)]


def yaml_value(value: Any) -> str:
    """`value` as a `--set` reads it back: a plain string where YAML reads it as that string, else JSON (YAML)."""
    if isinstance(value, str) and value and value.strip() == value and yaml.safe_load(value) == value:
        return value
    return json.dumps(value)


def describe_command(command: str, config, flags: Mapping[str, str], *, leading: Iterable[str] = (),
                     skip: Iterable[str] = (), always: Iterable[str] = ()) -> str:
    """`trivla-drake COMMAND` with the `leading` words, then the flag of each field in `flags` (dotted field -> flag)
    that differs from the schema's default (or is in `always` and not None), then `--set dotted.field=value` for
    every other field (but `skip`) that differs: a shell-quoted command line that runs `config`."""
    defaults = leaf_fields(type(config)())
    skip, always = set(skip), set(always)
    flagged, overrides = [], []
    for dotted, value in leaf_fields(config).items():
        shown = dotted in always and value is not None
        if dotted in skip or (not shown and dotted in defaults and value == defaults[dotted]):
            continue
        if dotted in flags:
            flagged += flag_words(flags[dotted], value)
        else:
            overrides += ["--set", f"{dotted}={yaml_value(value)}"]
    return " ".join(shlex.quote(word) for word in ["trivla-drake", command, *leading, *flagged, *overrides])


def _drake_yaml():
    """pydrake.common.yaml, imported when first needed: `train` and `export` run on machines without Drake, where
    a config of defaults still works."""
    try:
        import pydrake.common.yaml
    except ModuleNotFoundError as error:
        raise ModuleNotFoundError("config files and --set overrides are read with Drake's typed YAML loader: "
                                  "install Drake (pip install drake)", name=error.name) from error
    return pydrake.common.yaml


class _Misfit(Exception):
    """The dotted `field` of a mapping that does not fit its schema, and the `problem`."""

    def __init__(self, field: str, problem: str):
        super().__init__(f"{field}: {problem}")
        self.field, self.problem = field, problem


def _merge_checked(config, mapping: Mapping):
    """Drake's typed merge of `mapping` into a copy of `config`; _Misfit naming the field that does not fit."""
    misfit = _scalar_for_list(config, mapping, prefix="")
    if misfit is not None:  # Drake would read the string "abc" into a list as ["a", "b", "c"]
        raise _Misfit(*misfit)
    try:
        return _merge(config, mapping)
    except Exception:  # Drake's loader raises RuntimeError, TypeError, AssertionError, ... that may not name the field
        raise _Misfit(*_first_misfit(config, mapping, prefix="")) from None


def _merge(config, mapping: Mapping):
    """Drake's typed merge of `mapping` into a copy of `config` (raises whatever Drake raises)."""
    drake_yaml = _drake_yaml()
    return drake_yaml.yaml_load_typed(schema=type(config), data=drake_yaml.yaml_dump(dict(mapping)), defaults=config)


def _scalar_for_list(config, mapping: Mapping, *, prefix: str) -> Optional[tuple[str, str]]:
    """The dotted name of a list field of the dataclass `config` that `mapping` gives a scalar, and why; else None."""
    if not (dc.is_dataclass(config) and isinstance(mapping, Mapping)):
        return None
    hints = typing.get_type_hints(type(config))
    for name, value in mapping.items():
        hint = hints.get(name)
        if typing.get_origin(hint) is typing.Union:  # Optional[list[...]]
            hint = next((arg for arg in typing.get_args(hint) if arg is not type(None)), hint)
        if typing.get_origin(hint) is list and value is not None and not isinstance(value, list):
            return f"{prefix}{name}", f"{type(config).__name__}.{name} is a list: write [{value}], got {value!r}"
        misfit = _scalar_for_list(getattr(config, name, None), value, prefix=f"{prefix}{name}.")
        if misfit is not None:
            return misfit
    return None


def _nested(dotted: str, value: Any) -> dict:
    """{"a": {"b": value}} for "a.b"."""
    for name in reversed(dotted.split(".")):
        value = {name: value}
    return value


def _first_misfit(config, mapping: Mapping, *, prefix: str) -> tuple[str, str]:
    """The dotted name of the first field of `mapping` that does not fit the dataclass `config`, and why."""
    if not isinstance(mapping, Mapping):
        return prefix.rstrip(".") or "(top)", f"expected a mapping of {type(config).__name__}'s fields, got {mapping!r}"
    names = [field.name for field in dc.fields(config)] if dc.is_dataclass(config) else None
    for name, value in mapping.items():
        dotted = f"{prefix}{name}"
        if names is not None and name not in names:
            close = difflib.get_close_matches(str(name), names, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else f" (fields: {', '.join(names)})"
            return dotted, f"{type(config).__name__} has no field {name!r}{hint}"
        current = getattr(config, name, None)
        if dc.is_dataclass(current) and isinstance(value, Mapping):
            try:
                _merge(current, value)
                continue
            except Exception:
                return _first_misfit(current, value, prefix=f"{dotted}.")
        try:
            _merge(config, {name: value})
        except Exception as error:
            message = _drake_message(error)
            got = "" if repr(value) in message else f" (got {value!r})"
            return dotted, f"{type(config).__name__}.{name}: {message}{got}"
    return prefix.rstrip(".") or "(top)", "does not fit the schema"


def _drake_message(error: Exception) -> str:
    """Drake's loader's error in words (some of its errors are bare asserts of the offending value)."""
    if isinstance(error, AssertionError):
        return "wrong kind of value"
    return re.sub(r"<class '([\w.]+)'>", r"\1", str(error)) or type(error).__name__
