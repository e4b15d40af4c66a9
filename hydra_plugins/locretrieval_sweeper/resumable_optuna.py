"""The project's Hydra sweeper: an Optuna study of what train.py returns, on Optuna's ask-and-tell
interface (``hydra/sweeper=optuna``, configs/hydra/sweeper/optuna.yaml; ``hparams_search=localization``).
Rerunning the command of a killed or failed sweep goes on with its study: `locretrieval.training.sweeps.optimize`.

Hydra imports this module at every start (its plugin scan): the study's modules only when it sweeps.
"""

from typing import Any, List

from hydra.core.plugins import Plugins
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig


class ResumableOptunaSweeper(Sweeper):
    """Trials in batches of ``hydra.sweeper.n_jobs`` through the configured launcher, until
    ``hydra.sweeper.n_trials`` completed; its keys are `locretrieval.training.sweeps.SweepSettings`."""

    def __init__(self, **settings: Any) -> None:  # read from the config in `sweep`, checked there
        self.config: DictConfig | None = None
        self.launcher: Any = None

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        self.config = config
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config
        )

    def sweep(self, arguments: List[str]) -> None:
        from locretrieval.training.sweeps import optimize

        optimize(self.config, list(arguments), self.launcher.launch)
