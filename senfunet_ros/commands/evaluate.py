"""`senfunet evaluate`: the paper's tables on simulated rooms, ablations, plus the figure."""
from __future__ import annotations

import argparse
import sys

HELP = ("evaluate on simulated rooms: table (MSE, MAD, IoU, Acc, F, P, R), ablations, spread over rooms, "
        "asynchronous test, figure")


def _error(text: str) -> int:
    """An error, on stderr; the exit code 2."""
    print(f"senfunet evaluate: {text}", file=sys.stderr)
    return 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--weights", default="default", metavar="NAME|PATH",
                        help="weights: 'default' (senfunet_core/weights/tof_stereo.pt), 'paper' (the paper-exact "
                             "12-input model, tof_stereo_paper.pt), a .pt path, or 'none' (untrained)")
    parser.add_argument("--set", dest="seed_set", choices=("validation", "held-out"), default="validation",
                        help="rooms: 'validation' (900-905, where choices are made; default) or 'held-out' "
                             "(6001-6008, to be scored once at the end)")
    parser.add_argument("--scenes", type=int, default=None, metavar="N", help="only the first N rooms of the set")
    parser.add_argument("--ablations", action="store_true",
                        help="also: feature nets seeded / zeroed, the other shipped model (TSDF input on/off)")
    parser.add_argument("--out", default="docs", metavar="DIR",
                        help="writes DIR/results.md and DIR/figures/evaluation.png (default: docs)")
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="simulated seconds per room")
    parser.add_argument("--frame-stride", type=int, default=None, metavar="K",
                        help="integrate every K-th frame of each sensor")
    parser.add_argument("--no-async", action="store_true", help="skip the asynchronous test")
    parser.add_argument("--seeds-weights", nargs="+", default=None, metavar="PATH",
                        help="the spread over training seeds instead of the tables: score --weights and these weights "
                             "files (the same recipe trained with other seeds, `senfunet train --seed N`) on the set's "
                             "rooms and write that section of DIR/results.md, keeping the rest of the file")
    parser.add_argument("--cache-dir", default="~/.cache/senfunet", metavar="DIR",
                        help="simulated datasets cache ('none' to simulate without caching)")


def run(args: argparse.Namespace) -> int:
    import dataclasses
    from pathlib import Path

    from senfunet_core import networks
    from senfunet_core.errors import InputError
    from senfunet_core.learning.evaluation import (COLUMNS, SEED_SETS, EvaluationConfig, bar_check, evaluate,
                                                   goal_check, labelled)
    from senfunet_core.learning.report import results_markdown, seed_sections, training_notes
    from senfunet_core.metrics import format_table

    seeds = SEED_SETS[args.seed_set]
    if args.scenes is not None and not 1 <= args.scenes <= len(seeds):
        return _error(f"--scenes must be 1..{len(seeds)} for --set {args.seed_set}, got {args.scenes}")
    try:
        weights = networks.resolve_weights(args.weights)
    except InputError as err:
        return _error(str(err))
    config = EvaluationConfig(seeds=seeds[:args.scenes] if args.scenes else seeds, seed_set=args.seed_set,
                              ablations=args.ablations,
                              cache_dir=None if str(args.cache_dir).lower() == "none" else args.cache_dir)
    changes = {}
    if args.duration is not None:
        changes["duration_s"] = args.duration
    if args.frame_stride is not None:
        changes["frame_stride"] = args.frame_stride
    if args.no_async:
        changes["async_tof_divisors"] = ()
    config = dataclasses.replace(config, **changes)
    out = Path(args.out)
    if args.seeds_weights:
        return _run_seed_spread(args, weights, config, out)
    figure = out / "figures" / "evaluation.png"
    command = _command_line()
    out.mkdir(parents=True, exist_ok=True)

    def write(result) -> None:
        notes = training_notes(result.weights_source, "Training of the evaluated weights")
        if result.other_weights_source:
            notes += "\n" + training_notes(result.other_weights_source, "Training of the other shipped model")
        text = results_markdown(result, config, command.strip(), notes)
        old = out / "results.md"
        for section in seed_sections(old.read_text()) if old.is_file() else []:
            text = text.rstrip("\n") + "\n\n" + section  # the seed spread has its own command; keep it
        old.write_text(text)

    try:
        result = evaluate(weights, config, figure_path=figure, after_room=write)
    except InputError as err:
        return _error(str(err))
    print(format_table(labelled(result.rows), COLUMNS))
    for name, ok in {**goal_check(result.per_scene), **bar_check(result.rows)}.items():
        print(f"{name}: {'met' if ok else 'NOT met'}")
    write(result)
    print(f"wrote {out / 'results.md'} and {figure} in {result.seconds:.0f} s")
    return 0


def _command_line() -> str:
    """The command as typed (docs/results.md records what generated it)."""
    import shlex
    import sys

    if len(sys.argv) > 1 and sys.argv[1] == "evaluate":
        return "senfunet evaluate " + " ".join(shlex.quote(a) for a in sys.argv[2:])
    return "senfunet evaluate"


def _run_seed_spread(args: argparse.Namespace, weights, config, out) -> int:
    """`--seeds-weights`: the SenFuNet row of --weights and each listed file on the set's rooms, written
    as the seed-spread section of DIR/results.md (the section for this set is replaced, the rest kept)."""
    from pathlib import Path

    from senfunet_core.errors import InputError
    from senfunet_core.learning.evaluation import seed_spread, seed_summary
    from senfunet_core.learning.report import seed_section_key, seed_spread_markdown, splice_section

    if weights is None:
        return _error("--seeds-weights compares trained weights; --weights none is not one")
    missing = [p for p in args.seeds_weights if not Path(p).is_file()]
    if missing:
        return _error(f"--seeds-weights: no such file: {', '.join(missing)}; pass .pt files "
                      "written by `senfunet train --seed N --out PATH`")
    if args.ablations:
        print("senfunet evaluate: --seeds-weights scores the SenFuNet row only; --ablations is not run",
              file=sys.stderr)
    command = _command_line()
    out.mkdir(parents=True, exist_ok=True)
    path = out / "results.md"

    def write(result) -> None:
        old = path.read_text() if path.is_file() else "# Results\n"
        path.write_text(splice_section(old, seed_section_key(config), seed_spread_markdown(result, config, command)))

    try:
        result = seed_spread([weights, *args.seeds_weights], config, after_room=write)
    except InputError as err:
        return _error(str(err))
    write(result)
    for run, s in zip(result.runs, seed_summary(result)):
        print(f"{run.path}: mean F {s['F']:.2f}, {s['margin']:+.2f} over the better sensor "
              f"({s['rooms_above']} of {s['rooms']} rooms above it), {s['over_tsdf']:+.2f} over TSDF Fusion")
    print(f"wrote the seed spread ({config.seed_set}) into {path} in {result.seconds:.0f} s")
    return 0
