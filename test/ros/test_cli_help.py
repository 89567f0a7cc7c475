"""`senfunet --help` tells a user what the tool does and how to start, not how the package is laid out."""
from __future__ import annotations

from senfunet_ros.cli import build_parser


def test_top_level_help_is_for_users():
    text = build_parser().format_help()
    assert "senfunet_ros.commands" not in text
    assert "mesh" in text and "senfunet demo" in text and "COMMAND --help" in text
