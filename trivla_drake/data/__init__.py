"""trivla_drake.data: LeRobot-format (v3.0) dataset writer and reader, and training samples.

No pydrake here: pyarrow for parquet, OpenCV for mp4.
"""

from trivla_drake.data.checksums import DatasetCorruptError
from trivla_drake.data.lerobot_format import NotADatasetError
from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.data.lerobot_writer import LeRobotWriter
from trivla_drake.data.samples import TrainingSamples

__all__ = ["DatasetCorruptError", "LeRobotReader", "LeRobotWriter", "NotADatasetError", "TrainingSamples"]
