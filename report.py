"""Regenerate the report of one or several finished evaluation runs from their tables.

    python report.py outputs/evaluate/synthetic/densevlad/2025-01-01_12-00-00
    python report.py multirun/evaluate/2025-01-01_12-00-00 --output reports/all-models
    python report.py RUN_A RUN_B --groundtruth relative_pose

A directory without ``results.csv`` is searched for runs below it (a Hydra multirun).
"""

import argparse
import logging
from pathlib import Path

import locretrieval  # imports zlib before pycolmap; see locretrieval/__init__.py
from locretrieval.report import build_report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run directories, or folders holding them")
    parser.add_argument("--output", type=Path, help="report directory (default: the single run directory given)")
    parser.add_argument("--groundtruth", help="ground truth of the correlation analysis (default: relative pose)")
    parser.add_argument("--formats", nargs="+", default=["png", "pdf"], help="figure formats (default: png pdf)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="[%(levelname)s] %(name)s: %(message)s")
    if args.output is None:
        if len(args.runs) != 1:
            parser.error("--output is required when several runs are given")
        args.output = args.runs[0]
    print(build_report(args.runs, args.output, args.groundtruth, args.formats))


if __name__ == "__main__":
    locretrieval.exit_without_final_collection()
    main()
