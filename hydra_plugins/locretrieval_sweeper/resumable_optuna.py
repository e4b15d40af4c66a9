"""The Optuna sweeper of hydra-optuna-sweeper, resumable: ``hparams_search=localization``'s
``hydra.sweeper._target_``. What it adds is `locretrieval.training.sweeps.resume_study`."""

from typing import List

from hydra_plugins.hydra_optuna_sweeper.optuna_sweeper import OptunaSweeper


class ResumableOptunaSweeper(OptunaSweeper):
    """Rerunning the command of a killed sweep goes on with its study (stored in SQLite in the
    sweep folder): the finished trials are kept, the interrupted ones run again, ``n_trials`` in all."""

    def sweep(self, arguments: List[str]) -> None:
        from locretrieval.training.sweeps import resume_study

        resume_study(self.sweeper, arguments)
        return self.sweeper.sweep(arguments)
