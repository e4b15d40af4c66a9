"""What ``train.py`` returns, a sweep's objective: one metric of the validations after training
(``optimized_metric``), at its best or its last validation (``optimized_validation``)."""

from __future__ import annotations

import math
from collections.abc import Collection
from dataclasses import dataclass
from typing import Any

import pandas as pd

from locretrieval.config import ConfigError

#: ``optimized_validation``: the metric's highest value over the validations after training, or its last.
VALIDATIONS = ("best", "last")


@dataclass(frozen=True)
class Objective:
    """``metric``: a key validation logs (``val/<paradigm>/<method>/k<k>/<X>m_<Y>deg``, % localized,
    or ``val/retrieval/<groundtruth>/<metric>@<k>``; every one is better when higher); ``validation``:
    `VALIDATIONS`. Only validations after a training epoch count (epoch >= 0), those that logged
    the metric (the SfM paradigms' every ``sfm_every_n_epochs``)."""

    metric: str
    validation: str

    @classmethod
    def from_config(cls, cfg: Any) -> Objective:
        """The ``optimized_metric`` and ``optimized_validation`` of a train.py config (a config node
        or the plain mapping of a folder's file)."""
        validation = str(cfg["optimized_validation"])
        if validation not in VALIDATIONS:
            raise ConfigError(f"optimized_validation: {validation!r}; expected one of {list(VALIDATIONS)}")
        return cls(str(cfg["optimized_metric"]), validation)

    def check(self, logged: Collection[str]) -> None:
        """Raise `ConfigError` unless ``metric`` is among the metrics validation can log (``logged``)."""
        if self.metric not in logged:
            raise ConfigError(
                f"optimized_metric: {self.metric!r} is not logged by validation; with these paradigms, k, "
                f"thresholds and ground truths the metrics are: {', '.join(logged)}"
            )

    def value(self, table: pd.DataFrame) -> tuple[int, float]:
        """``(epoch, value)`` of ``metric`` at the ``validation`` chosen among those after training in
        ``table`` (``validation.csv``: ``epoch, metric, value``); `ValueError` naming the metric and
        the metrics there are when none logged it or a value is not finite."""
        trained = table[table["epoch"] >= 0]
        rows = trained[trained["metric"] == self.metric].sort_values("epoch", kind="stable")
        if rows.empty:
            available = sorted(set(trained["metric"]))
            raise ValueError(
                f"optimized_metric: {self.metric!r} was not logged by any validation after training "
                f"(epochs {sorted(set(trained['epoch']))}); the metrics logged: {', '.join(available) or 'none'}"
            )
        for epoch, value in zip(rows["epoch"], rows["value"]):
            if not math.isfinite(value):
                raise ValueError(
                    f"optimized_metric: {self.metric!r} is {value} at the validation after epoch {epoch}, "
                    f"not a finite number; the metrics logged: {', '.join(sorted(set(trained['metric'])))}"
                )
        chosen = rows.loc[rows["value"].idxmax()] if self.validation == "best" else rows.iloc[-1]
        return int(chosen["epoch"]), float(chosen["value"])
