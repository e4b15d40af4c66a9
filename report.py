"""Regenerate the report of one or several finished evaluation runs from their tables, or the
summary of train.py runs and sweeps.

    python report.py outputs/evaluate/synthetic/densevlad/2025-01-01_12-00-00
    python report.py multirun/evaluate/2025-01-01_12-00-00 --output reports/all-models
    python report.py RUN_A RUN_B --groundtruth relative_pose
    python report.py RUN --gallery queries=all k=10    # every query's top 10 in the galleries
    python report.py multirun/train/localization       # a train.py sweep: summary.md, .csv, .html
    python report.py TRAIN_RUN_A TRAIN_RUN_B --output reports/seeds   # train.py runs side by side

A directory without ``results.csv`` is searched for runs below it (a Hydra multirun).
"""

import argparse
import logging
from pathlib import Path

import locretrieval  # imports zlib before pycolmap; see locretrieval/__init__.py
from locretrieval.cli import reported_mistakes
from locretrieval.report import build_report
from locretrieval.report.gallery import run_gallery_settings
from locretrieval.report.tables import find_run_dirs
from locretrieval.training.summary import is_training_folder, write_summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run directories, or folders holding them")
    parser.add_argument("--output", type=Path, help="report directory (default: the single run directory given)")
    parser.add_argument("--groundtruth", help="ground truth of the correlation analysis (default: relative pose)")
    parser.add_argument("--formats", nargs="+", default=["png", "pdf"], help="figure formats (default: png pdf)")
    parser.add_argument(
        "--gallery",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="report.gallery settings replacing the first run's (e.g. queries=all k=10)",
    )
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="[%(levelname)s] %(name)s: %(message)s")
    logging.getLogger("alembic").setLevel(logging.WARNING)  # Optuna's storage imports it, which logs each plugin
    if args.output is None:
        if len(args.runs) != 1:
            parser.error("--output is required when several runs are given")
        args.output = args.runs[0]
    training = [is_training_folder(path) for path in args.runs]
    if any(training):
        if not all(training):
            parser.error("give either train.py runs and sweeps or evaluation runs, not both")
        print(write_summary(args.runs, args.output))
        return
    gallery, thumbnails = run_gallery_settings(find_run_dirs(args.runs)[0], args.gallery)
    print(
        build_report(
            args.runs, args.output, args.groundtruth, args.formats, gallery=gallery, thumbnail_cache=thumbnails
        )
    )


if __name__ == "__main__":
    locretrieval.exit_without_final_collection()
    with reported_mistakes():  # a folder that is not a run, a damaged table: its message, no traceback
        main()
