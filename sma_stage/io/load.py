"""One entry point for measured data: a CSV file or a rosbag2 (directory, .db3 or .mcap)."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from sma_stage.io.csv_io import read_csv
from sma_stage.io.rosbag_io import DEFAULT_INPUT_TOPIC, DEFAULT_JOINT, STORAGE_FILE_SUFFIXES, read_bag
from sma_stage.io.series import DEFAULT_MIN_SAMPLES, Series


def is_bag(path: str | os.PathLike) -> bool:
    """True for a directory or a .db3/.mcap file, which are read as rosbag2."""
    path = Path(path)
    return path.is_dir() or path.suffix in STORAGE_FILE_SUFFIXES


def load_series(
    path: str | os.PathLike,
    columns: Mapping[str, str | None] | None = None,
    input_topic: str | None = None,
    output_topic: str | None = None,
    joint_name: str = DEFAULT_JOINT,
    min_samples: int = DEFAULT_MIN_SAMPLES,
    default_input_topic: str = DEFAULT_INPUT_TOPIC,
) -> Series:
    """A checked Series from a CSV file (`columns` maps names) or a rosbag2 (topics, joint name).

    Options that do not apply to the kind of data found are ignored.
    """
    if is_bag(path):
        return read_bag(path, input_topic, output_topic, joint_name, min_samples, default_input_topic)
    return read_csv(path, columns, min_samples)
