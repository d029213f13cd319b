"""Every stage kind the product's recipes use, registered with the recipe runner: collect, evaluate and tables
(eval/stage_kinds.py), train, export, soup and refit (train/stage_kinds.py), and copy_dataset (here)."""

from trivla_drake.data.dataset_copy import DatasetCopyConfig, copy_dataset, dataset_copy_done, describe_dataset_copy
from trivla_drake.recipe import register_stage_kind


def register_all() -> None:
    """Registers the product's stage kinds (idempotent)."""
    import trivla_drake.eval.stage_kinds  # noqa: F401  (registers collect, evaluate, tables)
    import trivla_drake.train.stage_kinds  # noqa: F401  (registers train, export, soup, refit)

    register_stage_kind("copy_dataset", DatasetCopyConfig, run=_run_copy, is_done=_copy_done,
                        describe=describe_dataset_copy)


def _run_copy(config: DatasetCopyConfig, workdir: str) -> None:
    copy_dataset(config)


def _copy_done(config: DatasetCopyConfig, workdir: str) -> bool:
    return dataset_copy_done(config)
