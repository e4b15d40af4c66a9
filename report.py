"""Regenerate the report of one or several finished evaluation runs from their tables, or the
summary of train.py runs and sweeps.

    python report.py outputs/evaluate/synthetic/densevlad/2025-01-01_12-00-00
    python report.py multirun/evaluate/2025-01-01_12-00-00 --output reports/all-models
    python report.py RUN_A RUN_B --groundtruth relative_pose
    python report.py RUN --gallery queries=all k=10 --images data/   # galleries from the dataset's images
    python report.py multirun/train/localization       # a train.py sweep: summary.md, .csv, .html
    python report.py TRAIN_RUN_A TRAIN_RUN_B --output reports/seeds   # train.py runs side by side

A directory without ``results.csv`` is searched for runs below it (a Hydra multirun). Only files
inside the runs given are read, their YAML as written (no interpolation resolved), and only the
output folder is written: the galleries' images must lie inside a run or below an ``--images`` folder
(a shared run's ``images.csv`` may list any file), thumbnails are cached only under
``--thumbnail-cache``.
"""

import argparse
import logging
from pathlib import Path

import locretrieval  # imports zlib before pycolmap; see locretrieval/__init__.py
from locretrieval.build import build_report_gallery
from locretrieval.cli import reported_mistakes
from locretrieval.config import ConfigError
from locretrieval.report import build_report
from locretrieval.report.run_files import load_yaml, run_file
from locretrieval.report.tables import find_run_dirs
from locretrieval.report.training_runs import MULTIRUN_FILE, is_training_folder
from locretrieval.report.training_summary import write_summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run directories, or folders holding them")
    parser.add_argument("--output", type=Path, help="report directory (default: the single run directory given)")
    parser.add_argument("--groundtruth", help="ground truth of the correlation analysis (default: relative pose)")
    parser.add_argument(
        "--formats", nargs="*", default=["png", "pdf"], help="figure formats (default: png pdf; none given: no figures)"
    )
    parser.add_argument(
        "--gallery",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="report.gallery settings replacing the first run's (e.g. queries=all k=10)",
    )
    parser.add_argument(
        "--images",
        nargs="+",
        default=[],
        type=Path,
        metavar="DIR",
        help="folders whose images the galleries may read besides the runs' own (e.g. the dataset's folder)",
    )
    parser.add_argument("--thumbnail-cache", type=Path, help="folder caching the galleries' thumbnails (default: none)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="[%(levelname)s] %(name)s: %(message)s")
    logging.getLogger("alembic").setLevel(logging.WARNING)  # Optuna's storage imports it, which logs each plugin
    if args.output is None:
        if len(args.runs) != 1:
            parser.error("--output is required when several runs are given")
        args.output = args.runs[0]
    report(args)


def report(args: argparse.Namespace) -> None:
    """The summary of train.py runs and sweeps, or the report of evaluation runs (module docstring)."""
    for path in args.runs:  # its YAML within limits.yaml_nodes before the summary reads it
        if run_file(path, MULTIRUN_FILE).is_file():
            load_yaml(path / MULTIRUN_FILE)
    training = [is_training_folder(path) for path in args.runs]
    if any(training):
        if not all(training):
            raise ConfigError("give either train.py runs and sweeps or evaluation runs, not both")
        print(write_summary(args.runs, args.output))
        return
    gallery = build_report_gallery(find_run_dirs(args.runs)[0], args.gallery)
    print(
        build_report(
            args.runs,
            args.output,
            args.groundtruth,
            args.formats,
            gallery=gallery,
            thumbnail_cache=args.thumbnail_cache,
            image_roots=args.images,
        )
    )


if __name__ == "__main__":
    locretrieval.exit_without_final_collection()
    with reported_mistakes():  # a folder that is not a run, a damaged table: its message, no traceback
        main()
