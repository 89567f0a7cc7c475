"""The package's public surface: `__all__` names resolve, and importing it stays light."""
from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

import senfunet_core


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
