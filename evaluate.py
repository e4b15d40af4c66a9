"""Benchmark a global descriptor and the ground-truth rankings on a scene (Hydra entry point).

python evaluate.py                                  # DenseVLAD on the built-in synthetic scene
python evaluate.py data=baidu model=precomputed model.path=/path/to/global_features/AP-GeM
python evaluate.py -m model=densevlad,precomputed   # multirun sweep
"""

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

import locretrieval  # registers the config resolvers; imports zlib before pycolmap
from locretrieval.cli import check_command_line, reported_mistakes


@hydra.main(version_base="1.3", config_path="configs", config_name="evaluate")
def main(cfg: DictConfig) -> None:
    with reported_mistakes():  # a mistake of the user's: its message, no traceback
        from locretrieval.build import build_evaluation  # here, so that `--help` imports none of the heavy modules
        from locretrieval.evaluation import evaluate

        evaluate(build_evaluation(cfg), Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    locretrieval.exit_without_final_collection()
    check_command_line(Path(__file__).parent / "configs", "evaluate", sys.argv[1:])  # keys Hydra would refuse
    main()
