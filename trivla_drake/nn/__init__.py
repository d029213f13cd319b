"""trivla_drake.nn: TriVLA in PyTorch (never imports pydrake).

System 2 (`vision_language.py`): Eagle-2 design on SigLIP + Llama, Q_vl from a middle LLM layer.
System 3 (`dynamics.py`): SVD's spatio-temporal UNet read out in one pass from its up-blocks.
System 1 (`policy.py`): Video Former (eq. 4) + flow-matching DiT with embodiment-specific encoders.
`TriVLA` (`trivla.py`) composes them; its config schema in `config.py`, the named presets in `presets.py`;
checkpoints in `checkpoint.py` (their config as JSON: `config_dict.py`); Table-4-style timing in `benchmark.py`.
"""

from trivla_drake.nn.checkpoint import load_checkpoint, save_checkpoint
from trivla_drake.nn.config import TriVLAConfig
from trivla_drake.nn.normalization import NormalizationStats
from trivla_drake.nn.presets import PRESETS, make_config
from trivla_drake.nn.trivla import TriVLA

__all__ = [
    "PRESETS",
    "NormalizationStats",
    "TriVLA",
    "TriVLAConfig",
    "load_checkpoint",
    "make_config",
    "save_checkpoint",
]
