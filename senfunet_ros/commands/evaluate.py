"""`senfunet evaluate`: the paper's tables on simulated rooms, ablations, plus the figure."""
from __future__ import annotations

import argparse

HELP = ("evaluate on simulated rooms: table (MSE, MAD, IoU, Acc, F, P, R), ablations, spread over rooms, "
        "asynchronous test, figure")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--weights", default="default", metavar="NAME|PATH",
                        help="weights: 'default' (senfunet_core/weights/tof_stereo.pt), 'paper' (the paper-exact "
                             "12-input model, tof_stereo_paper.pt), a .pt path, or 'none' (untrained)")
    parser.add_argument("--set", dest="seed_set", choices=("validation", "held-out"), default="validation",
                        help="rooms: 'validation' (900-905, where choices are made; default) or 'held-out' "
                             "(4001-4008, to be scored once at the end)")
    parser.add_argument("--scenes", type=int, default=None, metavar="N", help="only the first N rooms of the set")
    parser.add_argument("--ablations", action="store_true",
                        help="also: feature nets seeded / zeroed, the other shipped model (TSDF input on/off)")
    parser.add_argument("--out", default="docs", metavar="DIR",
                        help="writes DIR/results.md and DIR/figures/evaluation.png (default: docs)")
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="simulated seconds per room")
    parser.add_argument("--frame-stride", type=int, default=None, metavar="K",
                        help="integrate every K-th frame of each sensor")
    parser.add_argument("--no-async", action="store_true", help="skip the asynchronous test")
    parser.add_argument("--cache-dir", default="~/.cache/senfunet", metavar="DIR",
                        help="simulated datasets cache ('none' to simulate without caching)")


def run(args: argparse.Namespace) -> int:
    import dataclasses
    import shlex
    import sys
    from pathlib import Path

    from senfunet_core import networks
    from senfunet_core.errors import InputError
    from senfunet_core.learning.evaluation import (COLUMNS, SEED_SETS, EvaluationConfig, bar_check, evaluate,
                                                   goal_check, labelled)
    from senfunet_core.learning.report import results_markdown, training_notes
    from senfunet_core.metrics import format_table

    seeds = SEED_SETS[args.seed_set]
    if args.scenes is not None and not 1 <= args.scenes <= len(seeds):
        print(f"senfunet evaluate: --scenes must be 1..{len(seeds)} for --set {args.seed_set}, got {args.scenes}")
        return 2
    try:
        weights = networks.resolve_weights(args.weights)
    except InputError as err:
        print(f"senfunet evaluate: {err}")
        return 2
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
    figure = out / "figures" / "evaluation.png"
    command = "senfunet evaluate " + " ".join(shlex.quote(a) for a in sys.argv[2:]) if len(sys.argv) > 1 and \
        sys.argv[1] == "evaluate" else "senfunet evaluate"
    out.mkdir(parents=True, exist_ok=True)

    def write(result) -> None:
        notes = training_notes(result.weights_source, "Training of the evaluated weights")
        if result.other_weights_source:
            notes += "\n" + training_notes(result.other_weights_source, "Training of the other shipped model")
        (out / "results.md").write_text(results_markdown(result, config, command.strip(), notes))

    try:
        result = evaluate(weights, config, figure_path=figure, after_room=write)
    except InputError as err:
        print(f"senfunet evaluate: {err}")
        return 2
    print(format_table(labelled(result.rows), COLUMNS))
    for name, ok in {**goal_check(result.per_scene), **bar_check(result.rows)}.items():
        print(f"{name}: {'met' if ok else 'NOT met'}")
    write(result)
    print(f"wrote {out / 'results.md'} and {figure} in {result.seconds:.0f} s")
    return 0
