"""The `senfunet` subcommands, one module each (see `senfunet_ros.cli`)."""
from __future__ import annotations

from pathlib import Path

SAMPLE_BAG = "sim_room"


def sample_bag() -> Path:
    """The bundled sample bag: this clone's (editable install), else bags/ of the working directory."""
    here = Path(__file__).resolve().parents[2] / "bags" / SAMPLE_BAG
    return here if here.exists() else Path.cwd() / "bags" / SAMPLE_BAG
