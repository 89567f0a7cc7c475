"""A ROS 1 bag is named as one, with the command that converts it."""
from __future__ import annotations

import pytest

from senfunet_ros.bagio import BagError, open_bag


def test_ros1_bag_is_named_with_the_conversion(tmp_path):
    bag = tmp_path / "robot.bag"
    bag.write_bytes(b"#ROSBAG V2.0\nE\x00\x00\x00")
    with pytest.raises(BagError, match=r"a ROS 1 bag; convert it to rosbag2 first: rosbags-convert --src .*robot\.bag"):
        with open_bag(bag):
            pass


def test_other_files_are_still_not_a_bag(tmp_path):
    other = tmp_path / "notes.txt"
    other.write_text("hello")
    with pytest.raises(BagError, match="not a bag"):
        with open_bag(other):
            pass
