"""Train a descriptor for localization with ground-truth relevance (Hydra entry point).

    python train.py                                # synthetic scene, EfficientNet-Lite0 + GeM, loss=ap
    python train.py loss=triplet train_relevance=frustum trainer.max_epochs=20
    python train.py -m loss=ap,triplet,contrastive,listwise      # a sweep, one directory per run
    python train.py ckpt_path=<run>/checkpoints/last.ckpt        # resume
"""

from pathlib import Path

import hydra
from omegaconf import DictConfig

import locretrieval  # noqa: F401  (imports zlib before pycolmap; see locretrieval/__init__.py)
from locretrieval.training.run import train


@hydra.main(version_base="1.3", config_path="configs", config_name="train")
def main(cfg: DictConfig) -> None:
    train(cfg, Path(cfg.output_dir))


if __name__ == "__main__":
    main()
