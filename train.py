"""Train a descriptor for localization with ground-truth relevance (Hydra entry point).

python train.py                                # synthetic scene, EfficientNet-Lite0 + GeM, loss=listwise
python train.py loss=triplet train_relevance=frustum trainer.max_epochs=20
python train.py -m loss=ap,triplet,contrastive,listwise      # a sweep, one directory per run
python train.py ckpt_path=<run>/checkpoints/last.ckpt        # resume
"""

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

import locretrieval  # registers the config resolvers; imports zlib before pycolmap


@hydra.main(version_base="1.3", config_path="configs", config_name="train")
def main(cfg: DictConfig) -> None:
    from locretrieval.training.run import train  # here, so that `--help` imports none of the heavy modules

    train(cfg, Path(cfg.output_dir))


if __name__ == "__main__":
    locretrieval.exit_without_final_collection()
    locretrieval.config.refuse_moved_keys(sys.argv[1:])  # a key of before 0.12, named with its new spelling
    main()
