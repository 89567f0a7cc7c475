"""The feature nets' CPU time per frame, this checkout's kernel against another revision's, in one process.

    .venv/bin/python bench/feature_net.py                 # against HEAD~1
    .venv/bin/python bench/feature_net.py --against e1377cc

Both kernels (`senfunet_core.feature_conv`; the other revision's file is loaded as a module of its
own) run the shipped feature nets on the same depth frames of the sample bag, alternately, one call
at a time; CPU time of this thread per call, median over the frames and repeats. Alternating in one
process keeps the machine's drift out of the ratio. Prints; writes nothing.
"""
from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench._common import ROOT, bag_frames, machine  # noqa: E402


def load_revision(revision: str, directory: Path):
    """senfunet_core/feature_conv.py as it was at `revision`, as a module."""
    source = subprocess.run(["git", "-C", str(ROOT), "show", f"{revision}:senfunet_core/feature_conv.py"],
                            check=True, capture_output=True, text=True).stdout
    path = directory / "feature_conv_other.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("feature_conv_other", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--against", default="HEAD~1", help="the git revision whose kernel is compared")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    from senfunet_core import feature_conv
    from senfunet_core.engine import SenFuNet

    engine = SenFuNet()
    frames = bag_frames(ROOT / "bags" / "sim_room", args.frames)
    with tempfile.TemporaryDirectory() as tmp:
        other = load_revision(args.against, Path(tmp))
        kernels = {"this checkout": feature_conv, args.against: other}
        spent: dict[tuple[str, str], list[float]] = {}
        largest_difference = 0.0
        for repeat in range(args.repeats + 1):  # the first pass compiles: not counted
            for frame in frames:
                net = engine.feature_nets[engine.config.sensors.index(frame.sensor)]
                convs, rgb = net.conv_arrays(), frame.rgb if net.uses_rgb else None
                rows = {}
                for name, kernel in kernels.items():
                    t0 = time.thread_time()
                    rows[name] = kernel.feature_net_rows(convs, frame.depth_m.astype(np.float32), rgb)
                    if repeat:
                        spent.setdefault((name, frame.sensor), []).append(time.thread_time() - t0)
                a, b = rows.values()
                largest_difference = max(largest_difference, float(np.abs(a - b).max()))
    print(f"Machine: {machine()}")
    print(f"{len(frames)} frames of the sample bag x {args.repeats} repeats, CPU ms per frame (median):")
    for sensor in dict.fromkeys(f.sensor for f in frames):
        ours, theirs = (1e3 * float(np.median(spent[(name, sensor)])) for name in kernels)
        print(f"  {sensor}: this checkout {ours:.2f}, {args.against} {theirs:.2f} (ratio {ours / theirs:.2f})")
    print(f"largest difference between the two kernels' outputs: {largest_difference:.2e}")


if __name__ == "__main__":
    main()
