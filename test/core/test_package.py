"""The package's public surface: `__all__` names resolve, importing it stays light, and set-up's
numba caches are never stale."""
from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

import senfunet_core

REPO = Path(__file__).resolve().parents[2]


def test_every_public_name_is_the_object_of_its_home_module():
    assert len(senfunet_core.__all__) == len(set(senfunet_core.__all__))
    for name in senfunet_core.__all__:
        home = importlib.import_module(f"senfunet_core.{senfunet_core._HOME[name]}")
        assert getattr(senfunet_core, name) is getattr(home, name), name
    assert set(senfunet_core.__all__) <= set(dir(senfunet_core))


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'Senfunet'"):
        senfunet_core.Senfunet  # noqa: B018


def test_importing_the_package_or_its_errors_loads_neither_torch_nor_numba():
    code = ("import sys, senfunet_core, senfunet_core.errors; "
            "print(sorted(m for m in ('torch', 'numba') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_set_up_drops_the_numba_caches_once_any_source_changed(tmp_path):
    """numba renews a cached kernel only when its own file changes, but kernels inline other modules'
    functions: set-up's compile step drops every cache file when any source differs from the stamp."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("compile_kernels", REPO / "scripts" / "compile_kernels.py")
    assert spec is not None and spec.loader is not None
    compile_kernels = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(compile_kernels)
    roots = [tmp_path / "core", tmp_path / "ros"]
    for root in roots:
        (root / "__pycache__").mkdir(parents=True)
        (root / "kernels.py").write_text("x = 1\n")
    caches = [roots[0] / "__pycache__" / "kernels.fill-10.py311.nbi",
              roots[1] / "__pycache__" / "kernels.g-3.py311.1.nbc"]

    def build() -> None:  # as main() does: compile (here: write the cache files), then stamp
        for cache in caches:
            cache.write_text("compiled")
        (roots[0] / "__pycache__" / compile_kernels.STAMP).write_text(digest + "\n")

    digest = compile_kernels.drop_stale_caches(roots)
    assert digest is not None
    build()
    assert compile_kernels.drop_stale_caches(roots) is None and all(c.is_file() for c in caches)  # current: kept
    (roots[1] / "kernels.py").write_text("x = 2\n")  # a source another kernel inlines changed
    digest = compile_kernels.drop_stale_caches(roots)
    assert digest is not None and not any(c.exists() for c in caches)
    build()
    (roots[0] / "new_module.py").write_text("")
    assert compile_kernels.drop_stale_caches(roots) is not None and not any(c.exists() for c in caches)
