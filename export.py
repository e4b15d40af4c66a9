"""Export rankings, descriptors and networks in the formats the field's tools read (Hydra entry point).

python export.py data=baidu model=precomputed model.feature_name=AP-GeM-LM18   # pairs files and descriptors
python export.py 'export=[onnx]' model=checkpoint model.weights=<run>/checkpoints/last.ckpt   # ONNX
"""

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

import locretrieval  # registers the config resolvers; imports zlib before pycolmap


@hydra.main(version_base="1.3", config_path="configs", config_name="export")
def main(cfg: DictConfig) -> None:
    from locretrieval.export.run import export  # here, so that `--help` imports none of the heavy modules

    export(cfg, Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    locretrieval.exit_without_final_collection()
    locretrieval.config.refuse_moved_keys(sys.argv[1:])
    main()
