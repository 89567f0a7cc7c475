"""A parameter file that is not YAML text is refused naming the file (and the place of a YAML error)."""
from __future__ import annotations

import pytest

from senfunet_ros.replay import load_settings


def test_binary_file_named(tmp_path):
    bad = tmp_path / "bag.mcap"
    bad.write_bytes(b"\x89MCAP0\r\n\xff\xfe")
    with pytest.raises(ValueError, match=r"bag\.mcap: not a text file; pass a YAML parameter file"):
        load_settings(bad)


def test_yaml_error_names_the_line(tmp_path):
    bad = tmp_path / "p.yaml"
    bad.write_text("senfunet:\n  ros__parameters:\n    voxel_size_m: [oops\n")
    with pytest.raises(ValueError, match=r"p\.yaml: not valid YAML \(line \d+, column \d+\)"):
        load_settings(bad)
