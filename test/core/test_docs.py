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


def test_the_engine_threading_model_names_every_thread_the_engine_starts():
    """The engine's docstring is the one place its threading model is described: each thread pool the
    engine's modules start is named there (the voxel-update thread of `integrator`, which writes the
    grid beside the integrating thread, was not)."""
    import re

    import senfunet_core.engine as engine

    sources = [path for path in (REPO / "senfunet_core").glob("*.py")]
    prefixes = {prefix for path in sources for prefix in re.findall(r'thread_name_prefix="([^"]+)"', path.read_text())}
    assert {"senfunet-features", "senfunet-update", "senfunet-alpha"} <= prefixes
    model = engine.__doc__.split("Threading model")[1]
    assert [prefix for prefix in sorted(prefixes) if f'"{prefix}"' not in model] == []
