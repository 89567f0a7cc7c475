"""`senfunet replay --out` that cannot be written is refused before the bag is fused."""
from __future__ import annotations

import time
from pathlib import Path

import pytest

from senfunet_ros.replay import replay_bag

SAMPLE = Path(__file__).resolve().parents[2] / "bags" / "sim_room"


def test_out_that_is_a_file_is_refused_at_once(tmp_path):
    target = tmp_path / "afile"
    target.write_text("keep me\n")
    t0 = time.monotonic()
    with pytest.raises(ValueError, match="is a file; pass a folder"):
        replay_bag(SAMPLE, target, progress=False)
    assert time.monotonic() - t0 < 10.0  # not after fusing the bag (~20-60 s)
    assert target.read_text() == "keep me\n"


def test_out_below_a_file_is_refused_at_once(tmp_path):
    (tmp_path / "afile").write_text("")
    with pytest.raises(ValueError, match="cannot create the folder"):
        replay_bag(SAMPLE, tmp_path / "afile" / "sub", progress=False)
