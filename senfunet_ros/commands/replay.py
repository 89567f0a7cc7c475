"""`senfunet replay BAG --out DIR`: offline, deterministic fusion of a recording."""
from __future__ import annotations

import argparse
import sys
import threading

HELP = "fuse a recorded bag offline as fast as possible: the fused mesh + stats (--compare: per-sensor and TSDF Fusion)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", metavar="BAG", help="rosbag2 folder (mcap or sqlite3) or a .mcap file")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder for the PLY files and stats.json")
    parser.add_argument("--params", metavar="FILE", help="node parameter file (default: the built-in defaults)")
    parser.add_argument("--gt", metavar="MESH",
                        help="ground-truth mesh (PLY): print F-score, precision, recall of each mesh")
    parser.add_argument("--weights", metavar="NAME|PATH",
                        help="network weights: 'default' (shipped), 'paper' (the paper-exact model), a .pt path or "
                             "'none' (untrained); overrides --params (default: the parameter file's, else 'default')")
    parser.add_argument("--threads", type=_positive_int, default=1, metavar="N",
                        help="torch CPU threads (default 1; the mesh bytes depend on it, keep it fixed)")
    parser.add_argument("--compare", action="store_true",
                        help="also write each sensor's mesh and the plain TSDF Fusion baseline (tsdf_fusion.ply), "
                             "for comparison: the baseline is integrated alongside, and the map is not bounded "
                             "(max_map_blocks is not applied: evicted blocks keep no per-sensor mesh): more time and "
                             "memory")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _stale_meshes(result, args: argparse.Namespace) -> list[str]:  # noqa: ANN001 - ReplayResult
    """Meshes in --out that this run did not write (an earlier run's, maybe with other parameters):
    comparison meshes beside the new mesh.ply, which would be compared with it, or a mesh.ply beside
    the stats.json of a run that fused nothing."""
    from pathlib import Path

    names = {*result.stats.get("sensors", {}), "tsdf_fusion", "mesh"}
    written = {Path(p).name for p in result.files.values()}
    return sorted(f"{n}.ply" for n in names if (Path(args.out) / f"{n}.ply").is_file() and f"{n}.ply" not in written)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number >= 1, got {text!r}")
    return value


def _error(text: str) -> int:
    print(f"senfunet replay: {text}", file=sys.stderr)
    return 2


# Set by Ctrl-C, SIGTERM and SIGHUP: the reading loop stops at its next message, and what was fused is saved.
# Not a KeyboardInterrupt at once: raised wherever the main thread is, it could cut the engine's work
# on a frame in half (and one raised in Python code that a C extension calls never reaches the loop).
_STOP = threading.Event()


def _interrupt(signum: int, frame: object) -> None:
    if _STOP.is_set():  # the second one: stop now, whatever is under way
        raise KeyboardInterrupt
    _STOP.set()
    print("senfunet replay: stopping; the meshes fused so far are being written (again to abort)", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    import signal

    from senfunet_ros.bagio import BagError

    # they stop a replay: what was fused is saved (SIGHUP: the terminal or ssh session closed)
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, _interrupt)
    from senfunet_ros.replay import DISTORTED_NOTE, drop_summary, replay_bag

    try:
        result = replay_bag(args.bag, args.out, params=args.params, gt=args.gt, progress=not args.no_progress,
                            threads=args.threads, weights=args.weights, compare=args.compare,
                            log=lambda text: print(f"senfunet replay: {text}", file=sys.stderr), stop=_STOP)
    except (BagError, ValueError) as err:
        return _error(str(err))
    except OSError as err:
        return _error(f"{err.filename or args.out}: {err.strerror}")

    stats = result.stats
    for sensor, c in stats["sensors"].items():
        reasons = drop_summary(c)
        undecodable = c["undecodable"].get("depth", 0)  # depth messages the bag holds that could not be read
        line = f"{sensor}: {c['integrated']} of {c['received'] + undecodable} frames fused"
        if undecodable:
            line += f"; {undecodable} undecodable"
        if reasons:
            line += f"; dropped: {reasons}"
        if c["pending_at_end"]:
            line += f"; {c['pending_at_end']} still waiting for a pose or camera_info at the end"
        if c["without_color"]:
            line += f"; {c['without_color']} fused without colour"
        if c["color_refused"]:
            line += f"; {c['color_refused']} fused without colour of another aspect ratio"
        if c["missing_depth"]:
            line += (f"; {c['missing_depth']} depth image(s) missing from the bag's regular stamps (the recorder or "
                     f"the driver lost them; the latest gap {c['missing_depth_gap']})")
        print(line)
        if c["distorted"]:
            print(f"{sensor}: note: {DISTORTED_NOTE}")
        for note in c["notes"].values():
            print(f"{sensor}: note: {note}")
    unfused = [sensor for sensor, c in stats["sensors"].items() if not c["integrated"]]
    if unfused and len(unfused) < len(stats["sensors"]):
        # one sensor alone: the paper's outlier filter keeps of its surface only what the net trusts
        # without the other sensor to back it, which may be little or nothing
        fused = result.meshes.get("mesh")
        print(f"senfunet replay: note: {', '.join(unfused)} fused no frame (see above), so mesh.ply holds only "
              "the surface the other sensor saw alone and the weighting net trusts"
              + (f" ({fused.n_faces} triangles)" if fused is not None else "")
              + "; --compare also writes each sensor's own mesh", file=sys.stderr)
    for path in result.files.values():
        print(f"wrote {path}")
    stale = _stale_meshes(result, args)
    if stale:
        compare = ", or pass --compare to rewrite the comparison meshes" if stale != ["mesh.ply"] else ""
        print(f"senfunet replay: note: {', '.join(stale)} in {args.out} {'is' if len(stale) == 1 else 'are'} from an "
              f"earlier run, not this one; delete {'it' if len(stale) == 1 else 'them'}{compare}", file=sys.stderr)
    t = stats["timings"]
    print(f"time: {t['total_s']:.1f} s (integration {t['integrate_s']:.1f} s, "
          f"{t['integrate_per_frame_ms']:.0f} ms per frame)")
    if stats["metrics"]:
        from senfunet_core.metrics import format_table

        gt = stats["gt"]
        print(f"mesh metrics against {args.gt}, cropped to the observed surface "
              f"({gt['vertices_observed']} of {gt['vertices']} vertices), tau 2 cm:")
        print(format_table(stats["metrics"], ["F", "P", "R"]), end="")
    elif args.gt and result.meshes:
        print(f"senfunet replay: no vertex of {args.gt} lies in the observed space; is it the right scene?",
              file=sys.stderr)
    if result.interrupted:
        print("senfunet replay: interrupted; wrote the meshes fused so far", file=sys.stderr)
        return 130
    if result.error:
        written = " (wrote the meshes fused so far)" if result.meshes else ""
        return _error(result.error + written)
    return 0
