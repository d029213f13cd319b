"""A TriVLA config as JSON data and back, as checkpoints store it: fields added since older checkpoints take the
value those were made with, fields of removed model variants are ignored when off and refused when on.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any

from trivla_drake.nn.config import TriVLAConfig


def config_to_dict(config: TriVLAConfig) -> dict[str, Any]:
    """The config as plain JSON-able data (tuples become lists)."""
    return dataclasses.asdict(config)


# Fields added after checkpoints were first saved, each with the value that reproduces what a checkpoint saved
# before the field existed was trained and run with (a missing field takes this value; any other missing field
# is refused, since its default may not be what the checkpoint was made with). Dotted paths under `config`.
FIELDS_OLDER_CHECKPOINTS_OMIT: dict[str, Any] = {
    "vision_language.dense_classes": 0,
    "vision_language.dense_subcells": 1,
    "dynamics.feature_noise": "random",  # before it, System 3 drew its one-pass noise anew each call
    "dynamics.feature_noise_seed": 0,
    "policy.tcp_features": False,
    "policy.vl_position_embedding": False,
    "policy.instruction_grounding": False,
    "policy.subgoal_offset": False,
    "policy.grounding_reads_gripper": False,
    "text_encoder": None,  # before it, every instruction was embedded from scratch
    "text_encoder_enters": "both",
}
# Fields of model variants no shipped checkpoint turned on, removed from the code (it is at git tag
# `research-archive`), each with its off value: a checkpoint that lists one at that value loads (the field is
# ignored); one that turns it on is refused, naming the field and the tag. Dotted paths under `config`.
REMOVED_FIELDS: dict[str, Any] = {
    "vision_language.image_token_norm": False,
    "policy.grounding_reads_tcp": False,
    "policy.subgoal_yaw": False,
    "policy.grounding_anchor_camera": (),
    "policy.grounding_anchor_wrist_camera": (),
}
# The git tag that keeps the code of the REMOVED_FIELDS.
RESEARCH_ARCHIVE_TAG = "research-archive"


def config_from_dict(data: dict[str, Any]) -> TriVLAConfig:
    """Rebuilds a config from `config_to_dict` data; unknown, ill-typed or missing fields raise ValueError
    naming the dotted field (only FIELDS_OLDER_CHECKPOINTS_OMIT may be missing: they take the value given there;
    REMOVED_FIELDS are ignored at their off value and refused otherwise)."""
    return _from_dict(TriVLAConfig, data, "config")


def _from_dict(cls: type, data: Any, where: str) -> Any:
    if not isinstance(data, dict):
        raise ValueError(f"{where} must be a JSON object; got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    data = without_removed_fields(data, REMOVED_FIELDS, where)
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"{where} has unknown fields {sorted(unknown)}; known: {sorted(names)}")
    kwargs = {name: _coerce(hints[name], value, f"{where}.{name}") for name, value in data.items()}
    for name in sorted(names - set(data)):
        dotted = f"{where}.{name}".partition(".")[2]
        if dotted not in FIELDS_OLDER_CHECKPOINTS_OMIT:
            raise ValueError(f"{where}.{name} is missing (only fields added since older checkpoints were "
                             f"saved may be, e.g. policy.subgoal_offset): add it with the value the model was made with")
        kwargs[name] = FIELDS_OLDER_CHECKPOINTS_OMIT[dotted]
    return cls(**kwargs)


def without_removed_fields(data: dict[str, Any], removed: dict[str, Any], where: str) -> dict[str, Any]:
    """`data` without the fields of `removed` ({dotted name under `where`: off value}) that hold their off value;
    ValueError naming a removed field that is on, and the git tag that keeps its code."""
    kept = {}
    for name, value in data.items():
        dotted = f"{where}.{name}".partition(".")[2] or name
        if dotted not in removed:
            kept[name] = value
            continue
        off = removed[dotted]
        if _plain(value) != _plain(off):
            raise ValueError(f"{where}.{name} is {value!r}: it turns on a variant this code no longer has (only "
                             f"{_plain(off)!r} loads); its code is at git tag `{RESEARCH_ARCHIVE_TAG}`")
    return kept


def _plain(value: Any) -> Any:
    """Tuples as lists (JSON gives lists), for comparing a saved value with an off value."""
    return list(value) if isinstance(value, (list, tuple)) else value


def _coerce(hint: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if dataclasses.is_dataclass(hint):
        return _from_dict(hint, value, where)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{where} must be a list; got {value!r}")
        return tuple(_coerce(args[0], v, where) for v in value)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        non_none = [a for a in args if a is not type(None)]
        return _coerce(non_none[0], value, where)
    if hint is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{where} must be true/false; got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{where} must be an integer; got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{where} must be a number; got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ValueError(f"{where} must be a string; got {value!r}")
        return value
    return value
