"""Train a descriptor for localization with ground-truth relevance (Hydra entry point).

python train.py                                # synthetic scene, EfficientNet-Lite0 + GeM, loss=listwise
python train.py loss=triplet train_relevance=frustum trainer.max_epochs=20
python train.py -m loss=ap,triplet,contrastive,listwise      # a sweep, one directory per run, summary.md
python train.py -m hparams_search=localization hydra/launcher=joblib_local   # an Optuna study of the objective
python train.py debug=quick                                  # under a minute: for trying a change
python train.py ckpt_path=<run>/checkpoints/last.ckpt        # resume
"""

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

import locretrieval  # registers the config resolvers; imports zlib before pycolmap
from locretrieval.cli import check_command_line, reported_mistakes


@hydra.main(version_base="1.3", config_path="configs", config_name="train")
def main(cfg: DictConfig) -> float | None:
    """Train; returns the ``optimized_metric`` (the objective of ``-m hparams_search=localization``)."""
    with reported_mistakes():  # a mistake of the user's: its message, no traceback
        from locretrieval.build import build_training  # here: `--help` imports no heavy module
        from locretrieval.cli import composed_training_scenes
        from locretrieval.training.run import optimized_value, train

        run = build_training(cfg, composed_training_scenes(cfg))
        return optimized_value(run.objective, train(run, Path(cfg.output_dir)))


if __name__ == "__main__":
    locretrieval.exit_without_final_collection()
    check_command_line(Path(__file__).parent / "configs", "train", sys.argv[1:])  # keys Hydra would refuse
    main()
