"""The training report's figure: ``validation.png``."""

from types import SimpleNamespace

import pandas as pd
from matplotlib.colors import to_hex

from locretrieval.report.training import draw_validation
from locretrieval.training.callbacks import HELD_OUT, SELECTION


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
