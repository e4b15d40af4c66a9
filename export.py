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
from locretrieval.cli import check_command_line, reported_mistakes


@hydra.main(version_base="1.3", config_path="configs", config_name="export")
def main(cfg: DictConfig) -> None:
    with reported_mistakes():  # a mistake of the user's: its message, no traceback
        from locretrieval.build import build_export  # here, so that `--help` imports none of the heavy modules
        from locretrieval.export.run import export

        export(build_export(cfg), Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    locretrieval.exit_without_final_collection()
    check_command_line(Path(__file__).parent / "configs", "export", sys.argv[1:])  # keys Hydra would refuse
    main()
