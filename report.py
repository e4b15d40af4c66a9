"""Regenerate the report of finished evaluation runs, or the summary of train runs and sweeps:
``locretrieval report`` (`locretrieval.commands`), from a clone.

    python report.py outputs/evaluate/synthetic/densevlad/2025-01-01_12-00-00
    python report.py multirun/evaluate/2025-01-01_12-00-00 --output reports/all-models
    python report.py RUN_A RUN_B --groundtruth relative_pose
    python report.py RUN --gallery queries=all k=10 --images data/   # galleries from the dataset's images
    python report.py multirun/train/localization       # a train sweep: summary.md, .csv, .html
    python report.py TRAIN_RUN_A TRAIN_RUN_B --output reports/seeds   # train runs side by side
"""

import sys

from locretrieval.commands import main

if __name__ == "__main__":
    main(["report", *sys.argv[1:]])
