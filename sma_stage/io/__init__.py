"""Reading and writing data: CSV, rosbag2, parameter files; every write is atomic."""
