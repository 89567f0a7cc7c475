"""The sample recording bags/sim_room is what scripts/make_sample_bag.sh makes with the current simulator."""
from __future__ import annotations

import hashlib
import os
import re
import subprocess
from pathlib import Path

import pytest

from senfunet_ros.bagio import open_bag, write_sequence_bag

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


def _records(bag: Path) -> list[tuple[str, int, str]]:
    with open_bag(bag) as reader:
        return [(m.topic, m.log_time_ns, hashlib.sha256(m.data).hexdigest()) for m in reader.messages()]


def _hash(records: list[tuple[str, int, str]]) -> str:
    return hashlib.sha256(repr(sorted(records)).encode()).hexdigest()


def test_sample_bag_starts_with_a_regenerated_prefix(tmp_path: Path) -> None:
    """The script's recording, regenerated for its pose streams and first ToF frames only (a few
    seconds), hashes the same as those messages in the committed bag."""
    from senfunet_core.learning import simulator as sim

    settings = _script_settings()
    seed = int(settings["seed"])
    seq = sim.simulate_sequence(sim.make_scene(seed), seed, duration_s=float(settings["duration"]),
                                tof_rate_hz=float(settings["tof_rate"]),
                                stereo_rate_hz=float(settings["stereo_rate"]), tof_prefix_frames=PREFIX_TOF_FRAMES)
    assert [f.sensor for f in seq.frames] == ["tof"] * PREFIX_TOF_FRAMES
    regenerated = _records(write_sequence_bag(seq, tmp_path / "prefix"))
    keys = {(topic, stamp) for topic, stamp, _ in regenerated}
    committed = [r for r in _records(SAMPLE) if (r[0], r[1]) in keys]
    depth = [r for r in regenerated if r[0] == "/tof/depth"]
    assert len(depth) == PREFIX_TOF_FRAMES and len(regenerated) > 500  # poses of both sensors, the ToF frames
    assert len(committed) == len(regenerated), "the committed bag lacks messages the simulator makes"
    assert _hash(committed) == _hash(regenerated), (
        "bags/sim_room is not what the current simulator makes: run bash scripts/make_sample_bag.sh")


def test_a_changed_frame_changes_the_prefix_hash(tmp_path: Path) -> None:
    """The hash sees one changed depth pixel (so the check above can fail)."""
    from senfunet_core.learning import simulator as sim

    settings = _script_settings()
    seed = int(settings["seed"])
    seq = sim.simulate_sequence(sim.make_scene(seed), seed, duration_s=float(settings["duration"]),
                                tof_rate_hz=float(settings["tof_rate"]),
                                stereo_rate_hz=float(settings["stereo_rate"]), tof_prefix_frames=1)
    before = _hash(_records(write_sequence_bag(seq, tmp_path / "a")))
    seq.frames[0].depth_m[128, 128] += 0.01
    assert _hash(_records(write_sequence_bag(seq, tmp_path / "b"))) != before


@pytest.mark.slow
def test_script_regenerates_the_sample_byte_for_byte(tmp_path: Path) -> None:
    subprocess.run(["bash", str(SCRIPT)], check=True, env={**os.environ, "OUT": str(tmp_path)}, cwd=REPO,
                   capture_output=True, timeout=540)
    for name in ("sim_room/metadata.yaml", "sim_room/sim_room.mcap", "sim_room_gt.ply"):
        made, committed = tmp_path / name, REPO / "bags" / name
        assert hashlib.sha256(made.read_bytes()).digest() == hashlib.sha256(committed.read_bytes()).digest(), name
