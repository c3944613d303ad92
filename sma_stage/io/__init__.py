"""Reading and writing data: CSV, rosbag2, parameter files; every write is atomic."""

from sma_stage.io.csv_io import read_csv, write_csv
from sma_stage.io.load import load_series
from sma_stage.io.rosbag_io import (
    BagRecorder,
    align_zero_order_hold,
    match_topic,
    read_bag,
    write_bag,
)
from sma_stage.io.series import Series, make_series

__all__ = [
    "BagRecorder",
    "Series",
    "align_zero_order_hold",
    "load_series",
    "make_series",
    "match_topic",
    "read_bag",
    "read_csv",
    "write_bag",
    "write_csv",
]
