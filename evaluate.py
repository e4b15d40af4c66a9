"""Benchmark a global descriptor and the ground-truth rankings on a scene (Hydra entry point).

    python evaluate.py                                  # DenseVLAD on the built-in synthetic scene
    python evaluate.py data=baidu model=precomputed model.path=/path/to/global_features/AP-GeM
    python evaluate.py -m model=densevlad,precomputed   # multirun sweep
"""

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

import locretrieval  # noqa: F401  (imports zlib before pycolmap; see locretrieval/__init__.py)
from locretrieval.evaluation import evaluate


@hydra.main(version_base="1.3", config_path="configs", config_name="evaluate")
def main(cfg: DictConfig) -> None:
    evaluate(cfg, Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    main()
