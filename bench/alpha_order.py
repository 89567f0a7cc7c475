"""Choosing EngineConfig.alpha_order: which stale blocks a short weighting-net budget serves first.

    .venv/bin/python bench/alpha_order.py                     # a simulated 12 x 8 m validation room;
                                                              # writes docs/performance.md
    .venv/bin/python bench/alpha_order.py --seconds 8 --blocks-per-update 300 1000 --no-write

The live node meshes once a second and then gives the weighting net a time budget; when the budget
cannot judge every block the frames changed, the order decides which meshed blocks wait. The goal
is "every meshed block judged within 3 s of its last change". To compare orders without the
machine's load in the figures, this runs the engine on virtual time: every frame of a simulated
validation room (seed < 1000) is integrated at its stamp, an update (alpha budget 0, as the node)
runs every second of stream time, then `refresh_alpha` with a budget of a fixed number of judged
blocks (the evaluation itself runs for real; only the budget's clock is virtual). After each update
it records the share of meshed blocks whose alpha has waited more than 3 s since their last change,
and the oldest wait (`SenFuNet.stats`). Prints a table and writes it into docs/performance.md.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench._common import ROOT, bag_frames, command, machine, simulated_bag, write_section  # noqa: E402


class _Clock:
    """Stands in for a module's `time`: monotonic is the stream time, perf_counter the budget's
    virtual seconds (one per `blocks_per_update` judged blocks); the rest is the real module."""

    def __init__(self) -> None:
        self.stream_s = 0.0
        self.budget_s = 0.0

    def monotonic(self) -> float:
        return self.stream_s

    def perf_counter(self) -> float:
        return self.budget_s

    def __getattr__(self, name: str) -> Any:
        return getattr(time, name)


def run(frames: list, order: str, blocks_per_update: int) -> dict:
    import senfunet_core.alpha_scheduler as scheduler_module
    import senfunet_core.engine as engine_module
    from senfunet_core.engine import SenFuNet
    from senfunet_ros.params import engine_config
    from senfunet_ros.params_file import load_settings

    clock = _Clock()
    saved = engine_module.time, scheduler_module.time
    engine_module.time = scheduler_module.time = clock  # type: ignore[assignment]
    try:
        engine = SenFuNet(engine_config(load_settings(None), alpha_order=order, max_blocks=0))
        evaluate = engine.alpha.evaluate

        def costed(slots: np.ndarray):
            batch = evaluate(slots)
            clock.budget_s += int(batch.holds.sum()) / blocks_per_update
            return batch

        engine.alpha.evaluate = costed  # type: ignore[method-assign]
        t0_ns, next_update_s, rows = frames[0].stamp_ns, 1.0, []
        for frame in frames + [None]:
            stream_s = (frame.stamp_ns - t0_ns) / 1e9 if frame is not None else next_update_s
            while stream_s >= next_update_s:  # the node's mesh timer, then the net's budget
                clock.stream_s = next_update_s
                engine.update(alpha_budget_s=0)
                engine.refresh_alpha(1.0)
                stats = engine.stats()
                rows.append((stats["meshed_blocks"], stats["meshed_blocks_unjudged_over_3s"],
                             stats["oldest_unjudged_change_s"], stats["meshed_blocks_alpha_current"]))
                next_update_s += 1.0
            if frame is not None:
                clock.stream_s = stream_s
                engine.integrate(frame.sensor, frame.depth_m, frame.K, frame.T_world_camera, frame.rgb)
    finally:
        engine_module.time, scheduler_module.time = saved
    meshed, waiting, oldest, current = (np.array(column, float) for column in zip(*rows))
    return {"waiting_share": float(np.mean(waiting / np.maximum(meshed, 1))),
            "waiting_share_end": float(waiting[-1] / max(meshed[-1], 1)),
            "oldest_median_s": float(np.median(oldest)), "oldest_max_s": float(oldest.max()),
            "current_end": float(current[-1] / max(meshed[-1], 1)), "judged": engine.counters["alpha_blocks"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=901, help="validation room (< 1000)")
    ap.add_argument("--room", type=float, nargs=3, default=[12.0, 8.0, 2.8])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--blocks-per-update", type=int, nargs="+", default=[500, 1500],
                    help="the budget: blocks judged after each mesh update")
    ap.add_argument("--orders", nargs="+", default=["latest", "longest_waiting"])
    ap.add_argument("--cache", default=str(ROOT / "bench" / ".cache"))
    ap.add_argument("--no-write", action="store_true", help="print only; do not touch docs/performance.md")
    args = ap.parse_args()
    if args.seed >= 1000:
        raise SystemExit(f"seed {args.seed} is held out: choose defaults on validation rooms (< 1000) only")
    import torch

    torch.set_num_threads(1)
    bag = simulated_bag(Path(args.cache), name="alpha_order", seed=args.seed, room=tuple(args.room),
                        seconds=args.seconds, tof_rate_hz=15.0, stereo_rate_hz=20.0)
    frames = sorted(bag_frames(bag), key=lambda f: f.stamp_ns)
    lines = [f"Machine: {machine()}", "", f"Command: `{command()}`", "",
             f"Virtual time (see the script's docstring): a simulated validation room (seed {args.seed}, "
             f"{' x '.join(f'{v:g}' for v in args.room)} m, {args.seconds:g} s, {len(frames)} depth frames, every one "
             "integrated at its stamp); a mesh update every second of stream time, then the weighting net judges "
             "at most the given number of blocks. Waiting: a meshed block whose alpha is not up to date, counted "
             "from the oldest frame of the schedule that last made it stale.", "",
             "| blocks judged per update | alpha_order | meshed blocks waiting > 3 s: mean over updates / at the end "
             "| oldest wait: median over updates / max (s) | meshed blocks up to date at the end | blocks judged |",
             "|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    for budget in args.blocks_per_update:
        for order in args.orders:
            r = run(frames, order, budget)
            lines.append(f"| {budget} | {order} | {100 * r['waiting_share']:.1f}% / "
                         f"{100 * r['waiting_share_end']:.1f}% "
                         f"| {r['oldest_median_s']:.1f} / {r['oldest_max_s']:.1f} | {100 * r['current_end']:.0f}% "
                         f"| {r['judged']} |")
            print(lines[-1], flush=True)
    if not args.no_write:
        write_section("Weighting-net order under a budget", "\n".join(lines))


if __name__ == "__main__":
    main()
