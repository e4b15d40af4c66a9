"""The training report (`locretrieval.report.training`): the gap table, every name it writes escaped;
its figure, ``validation.png``."""

from types import SimpleNamespace

import helpers
import numpy as np
import pandas as pd
import pytest
from matplotlib.colors import to_hex

from locretrieval.config import validated
from locretrieval.report.training import draw_validation
from locretrieval.training.callbacks import HELD_OUT, SELECTION


def test_the_gap_table_gives_the_share_of_the_gap_to_the_ground_truth_that_training_closed():
    from types import SimpleNamespace

    from training_runs import outcomes

    from locretrieval.metrics.uncertainty import default_uncertainty
    from locretrieval.report.training import TrainingReportSettings, gap_table

    p1, local, glob = "approximation/ewb/k3/5m_10deg", "local_sfm/pnp/k10/0.25m_2deg", "global_sfm/pnp/k5/0.25m_2deg"
    n = 50
    validations = [  # before training and two epochs; the SfM paradigms validated before training and at the last
        {p1: outcomes(10, n), local: outcomes(50, n), glob: outcomes(70, n)},
        {p1: outcomes(20, n)},
        {p1: outcomes(40, n), local: outcomes(60, n)},
    ]
    reference = {
        "densevlad": {p1: outcomes(20, n), local: outcomes(40, n)},
        "gt_relative_pose": {p1: outcomes(60, n), local: outcomes(100, n)},
        "gt_co_observation": {local: outcomes(80, n)},
    }
    validation = SimpleNamespace(
        outcomes=validations,
        reference_outcomes=reference,
        splits={"val": "all"},
        subsets={"all": np.ones(n, dtype=bool)},
        settings=SimpleNamespace(metrics=SimpleNamespace(uncertainty=default_uncertainty())),
    )
    report = validated(TrainingReportSettings, helpers.compose_config("train").report, "report")  # the default rows
    table = gap_table(validation, report).set_index("metric")
    assert list(table.index) == [p1, local]  # global SfM: validated once
    assert table.loc[p1, ["untrained", "trained", "densevlad", "groundtruth_value"]].tolist() == [10, 40, 20, 60]
    assert table.loc[p1, "gap_closed_pct"] == pytest.approx(100 * (40 - 20) / (60 - 20))
    assert table.loc[p1, "gap_closed_low_pct"] < 50 < table.loc[p1, "gap_closed_high_pct"]
    assert table.loc[local, "groundtruth"] == "gt_co_observation"  # 2a: the co-observation upper bound
    assert table.loc[local, "gap_closed_pct"] == pytest.approx(100 * (60 - 40) / (80 - 40))
    assert set(table["split"]) == {"all"} and set(table["num_queries"]) == {n}
    # the local SfM row: the ground truth below the baseline, a trained model below both: no gap to close
    reference["densevlad"][local] = outcomes(37.5 * 1.0, 16)
    reference["gt_co_observation"][local] = outcomes(31.25, 16)
    validations[0][local], validations[2][local] = outcomes(18.75, 16), outcomes(25.0, 16)
    validation.subsets = {"all": np.ones(16, dtype=bool)}
    for entries in (validations, [reference["densevlad"], reference["gt_relative_pose"]]):
        for entry in entries:
            entry[p1] = entry[p1][:16]
    below = gap_table(validation, report).set_index("metric").loc[local]
    assert np.isnan(below["gap_closed_pct"]) and below["gap_note"].startswith(
        "no gap to close: the ground truth (31.2 %) is below densevlad (37.5 %) on these 16 queries"
    )


def test_the_training_report_escapes_every_name_it_writes(tmp_path):
    from types import SimpleNamespace

    from locretrieval.metrics.uncertainty import default_uncertainty
    from locretrieval.report.training import TrainingReportSettings, write_training_report

    hostile = "<img src=x onerror=alert(1)>"
    metric = "val/approximation/ewb/k3/5m_10deg"
    history = [{"epoch": -1, metric: 10.0}, {"epoch": 0, metric: 40.0}]
    reference = {"densevlad": {metric: 20.0}, "gt_relative_pose": {metric: 60.0}, hostile: {metric: 30.0}}
    validation = SimpleNamespace(
        history_table=lambda: pd.DataFrame(
            [(-1, metric, 10.0, 1.0, 30.0, 10), (0, metric, 40.0, 20.0, 60.0, 10)],
            columns=["epoch", "metric", "value", "low", "high", "num_queries"],
        ),
        outcome_table=lambda: pd.DataFrame(columns=["ranking", "epoch", "metric", "query", "split", "localized"]),
        resolution=lambda: f"10 queries selected on {hostile}",
        history=history,
        reference=reference,
        reference_details={},
        galleries={},
        outcomes=[],
        reference_outcomes={},
        splits={"val": "all"},
        subsets={"all": np.ones(10, dtype=bool)},
        settings=SimpleNamespace(metrics=SimpleNamespace(uncertainty=default_uncertainty())),
    )
    report = validated(TrainingReportSettings, helpers.compose_config("train").report, "report")
    write_training_report(validation, tmp_path, report, {"val/local_sfm/pnp/k10/0.25m_2deg": hostile})
    text = (tmp_path / "report.md").read_text()
    # the resolution line, the reference row and the unfilled row
    assert "<img" not in text and text.count("&#60;img src=x onerror=alert(1)&#62;") == 3
    assert "| val/approximation/ewb/k3/5m_10deg " in text  # names without markup unchanged


def test_validation_png_draws_each_line_in_its_own_colour_over_whole_epochs(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    drawn = []
    monkeypatch.setattr(plt, "close", drawn.append)  # the figure, kept to be read
    key = "approximation/ewb/k3/5m_10deg"
    metric = f"{SELECTION}/{key}"
    table = pd.DataFrame(
        [(epoch, name, value, value - 5, value + 5) for epoch, value in ((-1, 10), (0, 20), (1, 30), (2, 35))
         for name, value in ((metric, value), (f"{HELD_OUT}/{key}", value - 2))],
        columns=["epoch", "metric", "value", "low", "high"],
    )  # fmt: skip
    references = {"densevlad": 25.0, "gt_relative_pose": 60.0, "gt_frustum": 55.0, "random": 5.0}
    validation = SimpleNamespace(
        reference={name: {metric: value} for name, value in references.items()},
        reference_details={name: {metric: [value - 4, value + 4]} for name, value in references.items()},
    )
    draw_validation(table, validation, [metric], tmp_path)
    assert (tmp_path / "validation.png").stat().st_size > 1000
    (figure,) = drawn
    (axis,) = figure.axes
    lines = {line.get_label(): line for line in axis.get_lines()}
    references_drawn = {name: to_hex(lines[name].get_color()) for name in references}
    assert len(set(references_drawn.values())) == len(references)  # a colour per reference line
    assert to_hex(lines["trained"].get_color()) not in references_drawn.values()
    assert lines["gt_relative_pose"].get_linestyle() == "--" and lines["densevlad"].get_linestyle() == ":"
    low, high = axis.get_xlim()
    ticks = [tick for tick in axis.get_xticks() if low <= tick <= high]
    assert ticks and all(float(tick).is_integer() for tick in ticks)  # epochs -1, 0, 1, 2: no -0.75
