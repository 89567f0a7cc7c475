"""`senfunet evaluate`: the paper's tables on held-out simulated scenes, plus the figure."""
from __future__ import annotations

import argparse

HELP = "evaluate on held-out simulated scenes: table (MSE, MAD, IoU, Acc, F, P, R), asynchronous test, figure"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--weights", default="default", metavar="PATH",
                        help="weights file (default: the shipped senfunet_core/weights/tof_stereo.pt; "
                             "'none' = untrained)")
    parser.add_argument("--scenes", type=int, default=3, metavar="N", help="held-out scenes (default 3, at most 6)")
    parser.add_argument("--out", default="docs", metavar="DIR",
                        help="writes DIR/results.md and DIR/figures/evaluation.png (default: docs)")
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="simulated seconds per scene")
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

    from senfunet_core.errors import InputError
    from senfunet_core.learning.evaluation import (COLUMNS, HELD_OUT_SEEDS, EvaluationConfig, bar_check, evaluate,
                                                   labelled, results_markdown, training_notes)
    from senfunet_core.metrics import format_table

    if not 1 <= args.scenes <= len(HELD_OUT_SEEDS):
        print(f"senfunet evaluate: --scenes must be 1..{len(HELD_OUT_SEEDS)}, got {args.scenes}")
        return 2
    weights = None if str(args.weights).lower() == "none" else args.weights
    config = EvaluationConfig(seeds=HELD_OUT_SEEDS[:args.scenes],
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
    try:
        result = evaluate(weights, config, figure_path=figure)
    except InputError as err:
        print(f"senfunet evaluate: {err}")
        return 2
    print(format_table(labelled(result.rows), COLUMNS))
    for name, ok in bar_check(result.rows).items():
        print(f"{name}: {'met' if ok else 'NOT met'}")
    command = "senfunet evaluate " + " ".join(shlex.quote(a) for a in sys.argv[2:]) if len(sys.argv) > 1 and \
        sys.argv[1] == "evaluate" else "senfunet evaluate"
    notes = training_notes(result.weights_source)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.md").write_text(results_markdown(result, config, command.strip(), notes))
    print(f"wrote {out / 'results.md'} and {figure} in {result.seconds:.0f} s")
    return 0
