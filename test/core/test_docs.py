"""Docs written by commands stay current."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_the_module_map_in_the_architecture_doc_is_current():
    result = subprocess.run([sys.executable, str(REPO / "scripts" / "module_map.py"), "--check"],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
