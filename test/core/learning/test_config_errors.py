"""A training config that is not a YAML mapping is a ValueError (`senfunet train`: one line, exit 2, no traceback)."""
from __future__ import annotations

import pytest

from senfunet_core.learning.training import load_config


@pytest.mark.parametrize("text, expected", [
    ("steps: [1, 2\n", r"not valid YAML \(line \d+, column \d+\)"),
    ("- steps\n- 3\n", "expected a mapping of training settings"),
])
def test_bad_yaml_is_a_value_error(tmp_path, text, expected):
    path = tmp_path / "train.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=expected):
        load_config(path)

