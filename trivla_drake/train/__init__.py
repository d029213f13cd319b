"""trivla_drake.train: the three training stages of TriVLA, in one process or under torchrun.

    from trivla_drake.train import TrainConfig, train
    train(TrainConfig(stage="video", data="demos", out="runs/video"))                         # System 3, eq. (1)
    train(TrainConfig(stage="vlm", out="runs/vlm", init="runs/video/final"))                  # System 2, VQA
    train(TrainConfig(stage="policy", data="demos", out="runs/policy", init="runs/vlm/final"))  # System 1, eq. (5)

`config.py` TrainConfig (nested, every field documented; YAML with --config / --set), `model_setup.py` the model a
run starts from, `stage_data.py` each stage's data, `optimization.py` AdamW and the schedule, `rng_state.py` the
random states a checkpoint keeps, `trainer.py` the loop, `checkpoints.py` atomic training checkpoints,
`sampler.py` the resumable distributed batch sampler, `datasets.py` clips and policy samples, `dataset_union.py`
several datasets in one policy run (`extra_data`), `features.py` the System 2/3 feature cache (`throughput.py` how
fast it and the policy stage run, for `bench --throughput`), `vqa.py`
simulator-generated visual questions, `export_job.py` / `model_soup.py` / `refit_job.py` the model-folder jobs,
`stage_kinds.py` the jobs as recipe stages, `cli_commands.py` the `train`, `export`, `soup`, `refit` subcommands.
"""

from trivla_drake.train.config import TrainConfig
from trivla_drake.train.trainer import train

__all__ = ["TrainConfig", "train"]
