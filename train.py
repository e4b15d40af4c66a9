"""Train a descriptor for localization with ground-truth relevance: ``locretrieval train``
(`locretrieval.commands`), from a clone.

python train.py                                # synthetic scene, EfficientNet-Lite0 + GeM, loss=listwise
python train.py loss=triplet train_relevance=frustum trainer.max_epochs=20
python train.py -m loss=ap,triplet,contrastive,listwise      # a sweep, one directory per run, summary.md
python train.py -m hparams_search=localization hydra/launcher=joblib_local   # an Optuna study of the objective
python train.py debug=quick                                  # under a minute: for trying a change
python train.py ckpt_path=<run>/checkpoints/last.ckpt        # resume
"""

import sys

from locretrieval.commands import main

if __name__ == "__main__":
    main(["train", *sys.argv[1:]])
