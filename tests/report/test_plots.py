"""The report's figures (`locretrieval.report.plots`): drawn once per format, their text inside their panel."""

import re

import numpy as np
import pandas as pd
import pytest
from report_runs import GROUNDTRUTH, localization, write_run

from locretrieval.report import build_report
from locretrieval.report.plots import MARGINS_INCHES, FigureFolder, _panels, curves_for_method, plot_query_violins


def test_ground_truth_without_a_method_is_drawn_with_ewb():
    results, _, _ = localization("netvlad", "descriptor")
    gt_results, _, _ = localization(GROUNDTRUTH, "groundtruth")
    curves = curves_for_method(pd.concat([results, gt_results]), "approximation", "csi")
    assert set(zip(curves["ranking"], curves["method"])) == {("netvlad", "csi"), (GROUNDTRUTH, "ewb")}


def test_a_figure_is_drawn_once_per_format_without_changing_its_layout(tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    draws = []
    original_draw = Figure.draw
    monkeypatch.setattr(Figure, "draw", lambda figure, renderer: draws.append(1) or original_draw(figure, renderer))
    figure, axes = _panels(3)
    layout = [axis.get_position().bounds for axis in axes]
    first = FigureFolder(tmp_path, ("png", "pdf")).save(figure, "a b")  # not a file name: made one, hashed
    assert first.parent == tmp_path and re.fullmatch(r"a_b-[0-9a-f]{8}\.png", first.name)
    assert first.with_suffix(".pdf").is_file()
    assert len(draws) == 2 and figure.get_layout_engine() is None
    assert [axis.get_position().bounds for axis in axes] == layout
    width, height = figure.get_size_inches()
    assert axes[0].get_position().x0 * width == pytest.approx(MARGINS_INCHES["left"])
    assert (1 - axes[2].get_position().x1) * width == pytest.approx(MARGINS_INCHES["right"])
    assert (axes[1].get_position().x0 - axes[0].get_position().x1) * width == pytest.approx(MARGINS_INCHES["between"])
    assert (1 - axes[0].get_position().y1) * height == pytest.approx(MARGINS_INCHES["top"])


def test_every_report_figure_keeps_its_text_inside_the_figure_and_its_own_panel(tmp_path, monkeypatch):
    checked = []
    original_save = FigureFolder.save

    def check_then_save(folder, figure, stem):
        figure.canvas.draw()
        renderer = figure.canvas.get_renderer()
        width, height = figure.bbox.width, figure.bbox.height
        boxes = [axis.get_tightbbox(renderer) for axis in figure.axes]  # ticks, labels, title, legend
        for box in boxes:
            assert 0 <= box.x0 and box.x1 <= width and 0 <= box.y0 and box.y1 <= height, stem
        rows = {}  # the panels of each row, by the bottom of their frames
        for axis, box in zip(figure.axes, boxes):
            rows.setdefault(round(axis.get_position().y0, 6), []).append(box)
        assert len(figure.axes) <= 3 * len(rows), stem  # at most three panels a row: legible at the page's width
        for row in rows.values():
            for left, right in zip(row, row[1:]):
                assert left.x1 < right.x0, stem  # no panel's text reaches into the next
        ordered = [rows[key] for key in sorted(rows, reverse=True)]  # top row first
        for upper, lower in zip(ordered, ordered[1:]):
            assert max(box.y1 for box in lower) < min(box.y0 for box in upper), stem  # nor into the row below
        for axis in figure.axes:  # nor one tick label into the next
            labels = sorted(
                (label.get_window_extent(renderer) for label in axis.get_xticklabels() if label.get_text()),
                key=lambda box: box.x0,
            )
            assert all(left.x1 < right.x0 for left, right in zip(labels, labels[1:])), stem
        assert [text.get_window_extent(renderer).y0 > max(box.y1 for box in boxes) for text in figure.texts] == [
            True
        ], stem
        checked.append(stem)
        return original_save(folder, figure, stem)

    monkeypatch.setattr(FigureFolder, "save", check_then_save)
    long_names = ["netvlad_pitts30k_vgg16_whitened", "apgem_resnet101_gldv1", "densevlad_multiscale"]  # violin labels
    build_report(
        [write_run(tmp_path / "run", long_names)], tmp_path / "report", figure_formats=["png"], figure_workers=1
    )
    assert len(checked) == 13 and any("violin" in stem for stem in checked)


def test_a_violin_panel_without_a_defined_coefficient_labels_its_rankings_inside_the_frame(tmp_path, monkeypatch):
    panels = []
    original_save = FigureFolder.save
    monkeypatch.setattr(
        FigureFolder,
        "save",
        lambda folder, figure, stem: panels.extend(figure.axes) or original_save(folder, figure, stem),
    )
    rows = pd.DataFrame(
        [
            ("toy", GROUNDTRUTH, "precision", paradigm, "pnp", ranking, value)
            for paradigm, values in (("global_sfm", [0.5, -0.2, 0.9]), ("local_sfm", [np.nan] * 3))
            for ranking in ("apgem", "netvlad")
            for value in values
        ],
        columns=["dataset", "groundtruth", "retrieval_metric", "paradigm", "method", "ranking", "coefficient"],
    )
    plot_query_violins(rows, FigureFolder(tmp_path, ("png",)), {"apgem": "#123456", "netvlad": "#abcdef"})
    for axis in panels:  # the empty panel's default limits (0, 1) put the second label on the frame
        assert axis.get_xlim() == (0.5, 2.5) and list(axis.get_xticks()) == [1, 2]
    from matplotlib.collections import LineCollection
    from matplotlib.colors import to_hex

    lines = [
        to_hex(collection.get_color()[0])
        for collection in panels[0].collections
        if isinstance(collection, LineCollection)
    ]
    assert len(lines) == 8 and set(lines) == {"#123456", "#abcdef"}  # bars, ends and median in the ranking's colour
    assert [label.get_text() for label in panels[1].get_xticklabels()] == ["apgem\n0/3 def.", "netvlad\n0/3 def."]
