"""`senfunet replay` refuses a --threads it would silently change (stats.json recorded the value given)."""
from __future__ import annotations

import pytest

from senfunet_ros.cli import build_parser


@pytest.mark.parametrize("value", ["0", "-3", "two"])
def test_threads_below_one_is_refused(value, capsys):
    with pytest.raises(SystemExit) as exit_info:
        build_parser().parse_args(["replay", "bag", "--out", "out", "--threads", value])
    assert exit_info.value.code == 2
    assert "--threads: must be a whole number >= 1" in capsys.readouterr().err


def test_threads_default_and_value():
    assert build_parser().parse_args(["replay", "bag", "--out", "out"]).threads == 1
    assert build_parser().parse_args(["replay", "bag", "--out", "out", "--threads", "2"]).threads == 2
