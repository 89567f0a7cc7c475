"""The sample recording bags/sim_room is what scripts/make_sample_bag.sh makes with the current simulator.

Equal message by message, up to the last bits of floating-point values: the simulator's pose
arithmetic rounds differently on CPUs of another kind (seen between CPUs with and without AVX-512),
so a pose regenerated on another machine can differ from the committed one in its last bits (and a depth pixel rendered
there may round to the next millimetre). Anything larger is a change of the simulator."""
from __future__ import annotations

import array
import os
import re
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rclpy.serialization import deserialize_message

from senfunet_ros.bagio import BagMessage, message_class, open_bag, write_sequence_bag

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "bags" / "sim_room"
SCRIPT = REPO / "scripts" / "make_sample_bag.sh"
PREFIX_TOF_FRAMES = 3


def _script_settings() -> dict[str, str]:
    """Seed, duration and rates as the script passes them to `senfunet simulate`."""
    text = SCRIPT.read_text()
    return {"seed": re.search(r"SEED=\$\{SEED:-(\d+)\}", text).group(1),
            "duration": re.search(r"DURATION=\$\{DURATION:-([\d.]+)\}", text).group(1),
            "tof_rate": re.search(r"--tof-rate ([\d.]+)", text).group(1),
            "stereo_rate": re.search(r"--stereo-rate ([\d.]+)", text).group(1)}


def _messages(bag: Path) -> dict[tuple[str, int], BagMessage]:
    with open_bag(bag) as reader:
        return {(m.topic, m.log_time_ns): m for m in reader.messages()}


# float fields (poses, intrinsics): the last bits may differ between CPUs, nothing more
_FLOAT_TOLERANCE = 1e-9
# depth pixels: at most this share may differ, by at most one step of their encoding (1 mm, or 1e-4 m in float)
_PIXEL_SHARE = {"16UC1": (1e-3, 1), "32FC1": (1e-3, 1e-4)}


def _fields(msg: object, prefix: str = "") -> dict[str, object]:
    """A ROS message's leaf fields by dotted name (nested messages flattened)."""
    if not hasattr(msg, "get_fields_and_field_types"):
        return {prefix: msg}
    out: dict[str, object] = {}
    for name in msg.get_fields_and_field_types():
        out.update(_fields(getattr(msg, name), f"{prefix}.{name}" if prefix else name))
    return out


def _difference(a: BagMessage, b: BagMessage) -> str | None:
    """Why two messages of one topic and stamp differ beyond rounding (None: they do not)."""
    if a.data == b.data:
        return None
    if a.msgtype != b.msgtype:
        return f"types {a.msgtype} and {b.msgtype}"
    cls = message_class(a.msgtype)
    fields_a, fields_b = (_fields(deserialize_message(m.data, cls)) for m in (a, b))
    encoding = fields_a.get("encoding")
    for name, value_a in fields_a.items():
        value_b = fields_b[name]
        if isinstance(value_a, float):
            if abs(value_a - value_b) > _FLOAT_TOLERANCE * max(1.0, abs(value_a)):
                return f"{name}: {value_a!r} != {value_b!r}"
        elif name == "data" and encoding in _PIXEL_SHARE:
            dtype = np.uint16 if encoding == "16UC1" else np.float32
            pixels_a, pixels_b = (np.frombuffer(bytes(v), dtype).astype(np.float64) for v in (value_a, value_b))
            share, step = _PIXEL_SHARE[encoding]
            off = np.abs(pixels_a - pixels_b) if len(pixels_a) == len(pixels_b) else np.full(1, np.inf)
            if off.max() > step or np.mean(off > 0) > share:
                return f"{name}: {np.count_nonzero(off)} pixels differ, by up to {off.max():g}"
        elif isinstance(value_a, (np.ndarray, array.array, list, tuple)):  # message arrays and sequences
            values_a, values_b = np.asarray(value_a), np.asarray(value_b)
            if values_a.dtype.kind == "f" and values_a.shape == values_b.shape:
                close = np.allclose(values_a, values_b, rtol=_FLOAT_TOLERANCE, atol=_FLOAT_TOLERANCE)
            else:
                close = np.array_equal(values_a, values_b)
            if not close:
                return f"{name}: the arrays differ"
        elif value_a != value_b:
            return f"{name}: {value_a!r} != {value_b!r}"
    return None  # the floats differ in their last bits only


def _differences(made: dict[tuple[str, int], BagMessage], committed: dict[tuple[str, int], BagMessage]) -> list[str]:
    """What differs beyond rounding between the messages of two bags (at most a few, to read)."""
    found = [f"{key}: {why}" for key in sorted(made)
             if (why := _difference(made[key], committed[key])) is not None]
    return found[:5]


def _prefix(tmp_path: Path, name: str, tof_frames: int, change: Callable[[Any], None] | None = None
            ) -> dict[tuple[str, int], BagMessage]:
    """The script's recording regenerated for its pose streams and first ToF frames only (a few
    seconds), with `change` applied to the simulated sequence first."""
    from senfunet_core.learning import simulator as sim

    settings = _script_settings()
    seed = int(settings["seed"])
    seq = sim.simulate_sequence(sim.make_scene(seed), seed, duration_s=float(settings["duration"]),
                                tof_rate_hz=float(settings["tof_rate"]),
                                stereo_rate_hz=float(settings["stereo_rate"]), tof_prefix_frames=tof_frames)
    assert [f.sensor for f in seq.frames] == ["tof"] * tof_frames
    if change is not None:
        change(seq)
    return _messages(write_sequence_bag(seq, tmp_path / name))


def test_sample_bag_starts_with_a_regenerated_prefix(tmp_path: Path) -> None:
    """The prefix regenerated now equals those messages of the committed bag (up to rounding)."""
    regenerated = _prefix(tmp_path, "prefix", PREFIX_TOF_FRAMES)
    sample = _messages(SAMPLE)
    depth = [key for key in regenerated if key[0] == "/tof/depth"]
    assert len(depth) == PREFIX_TOF_FRAMES and len(regenerated) > 500  # poses of both sensors, the ToF frames
    assert set(regenerated) <= set(sample), "the committed bag lacks messages the simulator makes"
    found = _differences(regenerated, sample)
    assert not found, ("bags/sim_room is not what the current simulator makes: run bash scripts/make_sample_bag.sh",
                       found)


@pytest.mark.parametrize("change", ["depth pixel", "pose"])
def test_a_changed_message_is_a_difference(tmp_path: Path, change: str) -> None:
    """One depth pixel 1 cm further, or one pose 1 um aside, is a difference (so the check above can fail)."""
    def changed(seq: Any) -> None:
        if change == "depth pixel":
            seq.frames[0].depth_m[128, 128] += 0.01
        else:
            seq.pose_T_world_camera["tof"][5][0, 3] += 1e-6

    before = _prefix(tmp_path, "a", 1)
    after = _prefix(tmp_path, "b", 1, changed)
    found = _differences(after, before)
    assert len(found) == 1 and ("data" if change == "depth pixel" else "position.x") in found[0], found


@pytest.mark.slow
def test_script_regenerates_the_sample(tmp_path: Path) -> None:
    """The script remakes the committed sample: the same messages (up to rounding), metadata and
    ground-truth mesh."""
    subprocess.run(["bash", str(SCRIPT)], check=True, env={**os.environ, "OUT": str(tmp_path)}, cwd=REPO,
                   capture_output=True, timeout=540)
    made, sample = _messages(tmp_path / "sim_room"), _messages(SAMPLE)
    assert set(made) == set(sample)
    assert not _differences(made, sample)
    for name in ("sim_room/metadata.yaml", "sim_room_gt.ply"):
        assert (tmp_path / name).read_bytes() == (REPO / "bags" / name).read_bytes(), name
