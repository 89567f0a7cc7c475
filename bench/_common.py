"""Shared helpers of the benchmark scripts: machine description and docs/performance.md sections."""
from __future__ import annotations

import os
import platform
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PERFORMANCE_MD = ROOT / "docs" / "performance.md"
HEADER = """# Performance

Written by the benchmark scripts (`bench/engine.py`, `bench/realtime.py`); each section is replaced
when its script runs again. Timings are wall-clock on the machine named in the section; on a
shared machine they are noisy (see the load average recorded with them).
"""


def vector_units() -> str:
    """The CPU's fastest arithmetic units for the nets, from /proc/cpuinfo's flags: the model name
    alone ("AMD EPYC") does not tell a CPU with bfloat16 units from one without."""
    try:
        flags = next(line for line in Path("/proc/cpuinfo").read_text().splitlines()
                     if line.startswith(("flags", "Features"))).split()
    except (OSError, StopIteration):
        return "instruction sets unknown"
    for flag, name in (("amx_bf16", "AMX"), ("avx512_bf16", "AVX-512 with bfloat16"), ("avx512f", "AVX-512"),
                       ("avx2", "AVX2"), ("bf16", "bfloat16"), ("asimd", "NEON")):
        if flag in flags:
            return name
    return "no AVX2"


def machine() -> str:
    import torch

    from senfunet_core.learning.evaluation import cpu_model

    cpu = f"{cpu_model()} ({vector_units()})"
    load = "n/a"
    try:
        load = " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        pass
    return (f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, torch {torch.__version__} "
            f"({torch.get_num_threads()} intra-op threads), load average {load} at the start")


def command() -> str:
    return " ".join([".venv/bin/python", os.path.relpath(sys.argv[0], ROOT), *sys.argv[1:]])


def write_section(title: str, body: str, path: Path = PERFORMANCE_MD) -> None:
    """Replace (or append) the section `## title` of docs/performance.md."""
    text = path.read_text() if path.is_file() else HEADER
    section = f"## {title}\n\n{body.strip()}\n"
    pattern = re.compile(rf"^## {re.escape(title)}\n.*?(?=^## |\Z)", re.S | re.M)
    if pattern.search(text):
        text = pattern.sub(lambda _: section + "\n", text).rstrip() + "\n"
    else:
        text = text.rstrip() + "\n\n" + section
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def simulated_bag(cache: Path, *, name: str, seed: int, room: tuple[float, float, float], seconds: float,
                  tof_rate_hz: float, stereo_rate_hz: float) -> Path:
    """A simulated two-sensor room as a bag under `cache` (made once, then reused)."""
    from senfunet_core.learning import simulator as sim
    from senfunet_ros.bagio import write_sequence_bag

    path = cache / f"{name}_seed{seed}_{'x'.join(f'{v:g}' for v in room)}_{seconds:g}s"
    if not (path / "metadata.yaml").is_file():
        print(f"simulating {seconds:g} s in a {room} m room (seed {seed}) into {path} ...", flush=True)
        seq = sim.simulate_sequence(sim.make_scene(seed, room_size_m=room), seed, duration_s=seconds,
                                    tof_rate_hz=tof_rate_hz, stereo_rate_hz=stereo_rate_hz)
        cache.mkdir(parents=True, exist_ok=True)
        write_sequence_bag(seq, path)
    return path


def min_median_max(values: list[float], fmt: str) -> str:
    """Runs' figures from run to run: "min / median / max", each in `fmt`."""
    import numpy as np

    values = sorted(values)
    return " / ".join(fmt.format(v) for v in (values[0], float(np.median(values)), values[-1]))


# bench/realtime.py's large room (bench/engine.py takes frames from it too)
LARGE_ROOM_SEED, LARGE_ROOM_M, LARGE_ROOM_SECONDS = 4243, (12.0, 8.0, 2.8), 30.0


def large_room_bag(cache: Path, *, seed: int = LARGE_ROOM_SEED, room_m: tuple[float, ...] = LARGE_ROOM_M,
                   seconds: float = LARGE_ROOM_SECONDS) -> Path:
    """The large simulated room's bag (ToF at 15 Hz, stereo at 20 Hz), made once under `cache`."""
    return simulated_bag(cache, name="large", seed=seed, room=(room_m[0], room_m[1], room_m[2]), seconds=seconds,
                         tof_rate_hz=15, stereo_rate_hz=20)


def bag_frames(bag: Path, limit: int | None = None) -> list:
    """`senfunet_ros.replay.bag_frames`, imported when a bench reads a bag."""
    from senfunet_ros.replay import bag_frames as frames

    return frames(bag, limit)
