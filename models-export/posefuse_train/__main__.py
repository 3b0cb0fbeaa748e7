"""python -m posefuse_train fit ...: the trainer's command line (docs/TRAINING.md)."""

from __future__ import annotations

import argparse
import sys

from . import __version__
from .recipe import builtin


def fit_parser() -> argparse.ArgumentParser:
    from .fit import __doc__ as doc

    p = argparse.ArgumentParser(
        prog="python -m posefuse_train fit",
        description=doc,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--train", required=True, help="training set (simulate / waymo convert output)")
    p.add_argument("--test", required=True, help="held-out set the bundle is scored on")
    p.add_argument("--out", required=True, help="the bundle directory to write")
    p.add_argument(
        "--recipe", default="cpu", help=f"a recipe file, or one of {', '.join(builtin())} (default cpu)"
    )
    p.add_argument(
        "--set",
        action="append",
        metavar="SECTION.KEY=VALUE",
        help="override one recipe value (repeatable), e.g. --set camera.steps=200",
    )
    p.add_argument("--work", help="the run's state: log, checkpoints (default: OUT.work)")
    p.add_argument("--device", default="auto", help="auto (CUDA when present), cpu, cuda or cuda:N")
    p.add_argument(
        "--amp",
        default="auto",
        choices=["auto", "bf16", "none"],
        help="auto: recipe's on CUDA, none on CPU",
    )
    p.add_argument("--resume", action="store_true", help="continue the run in --work")
    p.add_argument(
        "--stop-after",
        metavar="STAGE:STEP",
        help="stop once STAGE (camera, fusion, lidar) has done STEP steps (checkpoint written; --resume)",
    )
    p.add_argument(
        "--memory-mb",
        type=float,
        default=3000.0,
        help="memory for training shards: a larger set is read a window of shards at a time (default 3000)",
    )
    p.add_argument("--checkpoint-every", type=int, default=0, help="checkpoint interval (0: the recipe's)")
    p.add_argument("--name", default="default", help="the bundle's name")
    p.add_argument("--version", default=__version__, help="the bundle's version, which every response names")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    p.add_argument(
        "--facing-from",
        metavar="WORK",
        help="a finished fit's work directory, trained with --set point.rotate_deg=180: its point nets read "
        "the facing in front of this run's, so the bundle needs no box heading (docs/TRAINING.md)",
    )
    p.add_argument("--facing-turns", type=int, default=1, help="turns the facing nets answer at")
    p.add_argument("--facing-passes", type=int, default=1, help="refinement passes inside the point networks")
    p.add_argument(
        "--facing-agree-deg",
        type=float,
        default=0.0,
        help="keep the box frame where the facing net agrees with the heading within this many degrees",
    )
    p.add_argument(
        "--blend",
        action="store_true",
        help="the fusion graph answers the mean of the fusion and LiDAR-only nets (docs/TRAINING.md)",
    )
    return p


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: python -m posefuse_train fit --train DIR --test DIR --out BUNDLE [options]")
        print("       python -m posefuse_train fit --help")
        return 0 if argv else 2
    if argv[0] != "fit":
        print(f"unknown command {argv[0]!r}: the trainer's command is `fit`", file=sys.stderr)
        return 2
    from .fit import main_fit

    return main_fit(argv[1:], fit_parser())


if __name__ == "__main__":
    sys.exit(main())
