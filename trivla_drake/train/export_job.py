"""The `export` and `soup` jobs: a model folder (config.json + weights, loadable by `load_checkpoint`) written from one
checkpoint, or from the uniform weight average of several, with the job's config beside it as YAML
(export_config.yaml, soup_config.yaml).

No `from __future__ import annotations` here: the configs are loaded with Drake's `yaml_load_typed`.
"""

from dataclasses import dataclass, field
from pathlib import Path

EXPORT_CONFIG_FILE = "export_config.yaml"
SOUP_CONFIG_FILE = "soup_config.yaml"
REFIT_CONFIG_FILE = "refit_config.yaml"  # (refit_job.py writes it)
JOB_CONFIG_FILES = (EXPORT_CONFIG_FILE, SOUP_CONFIG_FILE, REFIT_CONFIG_FILE)
MODEL_FOLDER = "model (config.json and model.safetensors)"


@dataclass
class ExportConfig:
    """`trivla-drake export CHECKPOINT --out OUT`: a checkpoint's model without its optimizer state."""

    # The checkpoint folder (a run's final/ or checkpoints/step-N/).
    checkpoint: str = ""
    # The folder to write; an earlier export there is replaced once the new one is complete.
    out: str = ""
    # Replace `out` even when it holds other things than an earlier export (they are deleted; never the working
    # folder).
    overwrite: bool = False
    # The stored weights' dtype: float16 (half the size, as models/trivla_cpu), bfloat16 or float32; loading casts
    # back to float32.
    dtype: str = "float16"
    # Keep only System 2's LLM layers up to its read-out layer (select_layer): the same actions from a smaller file,
    # but no longer a start for the vlm stage.
    drop_unused_llm_layers: bool = False


@dataclass
class SoupConfig:
    """`trivla-drake soup CHECKPOINT... --out OUT`: the uniform weight average of checkpoints trained from one start."""

    # Two or more checkpoint folders with the same config.json and the same frozen Systems 2 and 3 (runs' final/).
    checkpoints: list[str] = field(default_factory=list)
    # As ExportConfig's.
    out: str = ""
    overwrite: bool = False
    # The stored weights' dtype (the average is taken in float32).
    dtype: str = "float16"
    # As ExportConfig's.
    drop_unused_llm_layers: bool = False


def check_model_folder_config(config, job: str) -> None:
    """ValueError naming the field of an export or soup config the job cannot run with."""
    from trivla_drake.nn.checkpoint import WEIGHT_DTYPES

    if not config.out:
        raise ValueError(f"{job}: out must name a folder")
    if config.dtype not in WEIGHT_DTYPES:
        raise ValueError(f"{job}: dtype must be one of {', '.join(WEIGHT_DTYPES)}; got {config.dtype!r}")


def run_export(config: ExportConfig) -> Path:
    """Writes the export `config` describes (after checking its out folder may be replaced); returns the folder."""
    from trivla_drake.train.checkpoints import export_checkpoint

    check_model_folder_config(config, "export")
    if not config.checkpoint:
        raise ValueError("export: checkpoint must name a checkpoint folder")
    check_out_folder(config)
    return export_checkpoint(config.checkpoint, config.out, weights_dtype=config.dtype,
                             drop_unused_llm_layers=config.drop_unused_llm_layers,
                             job_config=(EXPORT_CONFIG_FILE, config))


def run_soup(config: SoupConfig) -> Path:
    """Writes the soup `config` describes (after checking its out folder may be replaced); returns the folder."""
    from trivla_drake.train.model_soup import soup_checkpoints

    check_model_folder_config(config, "soup")
    check_out_folder(config)
    return soup_checkpoints(config.checkpoints, config.out, weights_dtype=config.dtype,
                            drop_unused_llm_layers=config.drop_unused_llm_layers, job_config=(SOUP_CONFIG_FILE, config))


def check_out_folder(config, *, flag: str = "--out", overwrite_flag: str = "--overwrite") -> None:
    """ValueError (naming `flag`, and `overwrite_flag` as the way out) unless `config.out` may be replaced: missing,
    empty, an earlier model export, or `overwrite`."""
    from trivla_drake.train.atomic_folder import check_replaceable_folder

    check_replaceable_folder(config.out, flag=flag, holds_earlier_output=holds_model_export, what=MODEL_FOLDER,
                             overwrite=config.overwrite, overwrite_flag=overwrite_flag)


def holds_model_export(folder) -> bool:
    """Whether `folder` holds just what `export`, `soup` and `refit` write: a checkpoint's config.json and weights
    (and its tokenizer folders), and at most the config of the job that wrote it."""
    from trivla_drake.nn.checkpoint import CONFIG_FILE, WEIGHTS_FILE, read_checkpoint_config

    names = {p.name for p in Path(folder).iterdir() if not (p.is_dir() and p.name.startswith("tokenizer_"))}
    jobs = names & set(JOB_CONFIG_FILES)
    if names - jobs != {CONFIG_FILE, WEIGHTS_FILE} or len(jobs) > 1:
        return False
    try:
        read_checkpoint_config(str(folder))
    except ValueError:
        return False
    return True


def holds_export_of(folder, config, file_name: str) -> bool:
    """Whether `folder` holds a complete model export whose job config (`file_name`) is `config`."""
    import yaml

    from trivla_drake.train.config import config_from_mapping

    path = Path(folder) / file_name
    if not (Path(folder).is_dir() and path.is_file() and holds_model_export(folder)):
        return False
    try:
        return config_from_mapping(type(config), yaml.safe_load(path.read_text()) or {}) == config
    except (ValueError, TypeError, yaml.YAMLError):
        return False
