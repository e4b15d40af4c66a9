"""What ``train.py`` returns, a sweep's objective: one metric of the validations after training
(``optimized_metric``), at its best or its last validation (``optimized_validation``), and what a
summary reports beside it: its interval, and the same metric on the held-out validation queries at
that validation (`ObjectiveFigures`), which took no part in choosing it."""

from __future__ import annotations

import math
from collections.abc import Collection
from dataclasses import dataclass
from typing import Any

import pandas as pd

from locretrieval.config import ConfigError

#: ``optimized_validation``: the metric's highest value over the validations after training, or its last.
VALIDATIONS = ("best", "last")
#: The prefixes of the metrics on the queries selected on and on the held-out ones (`callbacks`).
SELECTION_PREFIX, HELD_OUT_PREFIX = "val/", "held_out/"


@dataclass(frozen=True)
class ObjectiveFigures:
    """The objective of a run at its chosen validation (``epoch``): ``value`` with its interval
    (``low``, ``high``, NaN when the run kept none) over ``num_queries``; ``held_out``: the same metric
    on the held-out queries at that validation, ``(value, low, high, num_queries)``, or None."""

    epoch: int
    value: float
    low: float
    high: float
    num_queries: float
    held_out: tuple[float, float, float, float] | None


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

    @property
    def held_out_metric(self) -> str:
        """The objective's metric on the held-out validation queries."""
        return HELD_OUT_PREFIX + self.metric.removeprefix(SELECTION_PREFIX)

    def figures(self, table: pd.DataFrame) -> ObjectiveFigures:
        """The `ObjectiveFigures` of ``table`` (``validation.csv``; its interval columns absent in a run
        of an earlier version): `value`'s validation, and the held-out metric there."""
        epoch, value = self.value(table)

        def at_epoch(metric: str) -> pd.Series | None:
            rows = table[(table["epoch"] == epoch) & (table["metric"] == metric)]
            return rows.iloc[0] if len(rows) else None

        chosen = at_epoch(self.metric)
        interval = [float(chosen.get(column, math.nan)) for column in ("low", "high", "num_queries")]
        held = at_epoch(self.held_out_metric)
        held_out = (
            None
            if held is None
            else tuple(float(held.get(column, math.nan)) for column in ("value", "low", "high", "num_queries"))
        )
        return ObjectiveFigures(epoch, value, *interval, held_out)
