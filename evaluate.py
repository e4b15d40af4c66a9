"""Benchmark a global descriptor and the ground-truth rankings on a scene: ``locretrieval evaluate``
(`locretrieval.commands`), from a clone.

python evaluate.py                                  # DenseVLAD on the built-in synthetic scene
python evaluate.py data=baidu model=precomputed model.path=/path/to/global_features/AP-GeM
python evaluate.py -m model=densevlad,precomputed   # multirun sweep
"""

import sys

from locretrieval.commands import main

if __name__ == "__main__":
    main(["evaluate", *sys.argv[1:]])
