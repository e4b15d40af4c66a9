import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from report_runs import GROUNDTRUTH, KS, localization, write_run
from scipy import stats

from locretrieval.report import build_report
from locretrieval.report.markdown import pivot_localization
from locretrieval.report.plots import MARGINS_INCHES, FigureFolder, _panels, curves_for_method, plot_query_violins
from locretrieval.report.tables import load_runs


def test_ground_truth_without_a_method_is_drawn_with_ewb():
    results, _, _ = localization("netvlad", "descriptor")
    gt_results, _, _ = localization(GROUNDTRUTH, "groundtruth")
    curves = curves_for_method(pd.concat([results, gt_results]), "approximation", "csi")
    assert set(zip(curves["ranking"], curves["method"])) == {("netvlad", "csi"), (GROUNDTRUTH, "ewb")}


def test_pivot_localization_reads_the_table_with_k_as_rows_and_thresholds_as_columns():
    results, _, _ = localization("netvlad", "descriptor")
    pivot = pivot_localization(results, "global_sfm", "pnp")
    assert list(pivot.columns) == ["0.25 m, 2°", "5 m, 10°"] and list(pivot.index) == [("netvlad", k) for k in KS]
    row = results.set_index(["subset", "paradigm", "k", "position_threshold_m"]).loc[("all", "global_sfm", 5, 5.0)]
    # the share of the 6 queries with its Wilson interval, as scipy gives it
    interval = stats.binomtest(int(row["localized"]), 6).proportion_ci(method="wilson")
    expected = f"{row['localized_pct']:.1f} ({100 * interval.low:.1f}–{100 * interval.high:.1f})"
    assert pivot.loc[("netvlad", 5), "5 m, 10°"] == expected


def markdown_rows(path: Path) -> list[list[str]]:
    """The cells of a markdown table file, stripped."""
    return [[cell.strip() for cell in line.split("|")[1:-1]] for line in path.read_text().splitlines()]


def test_report_shows_the_best_over_k_first_and_narrow_tables_from_the_unchanged_tidy_csv(tmp_path):
    run = write_run(tmp_path / "run", ["netvlad"])
    tidy = (run / "results.csv").read_bytes()
    text = build_report([run], tmp_path / "report", figure_formats=["png"]).read_text()
    localization = text[text.index("## Localization") :]
    assert localization.index("Best % of queries localized over k") < localization.index("### toy: approximation, csi")
    best = markdown_rows(tmp_path / "report" / "tables" / "localization_best_over_k.md")
    assert best[0] == ["dataset", "paradigm", "method", "ranking", "0.25 m, 2°", "5 m, 10°"]
    results = pd.read_csv(run / "results.csv")
    ewb = results.query("subset == 'all' and paradigm == 'approximation' and method == 'ewb' and ranking == 'netvlad'")
    best_ewb = ewb.sort_values(["localized_pct", "k"], ascending=[False, True]).groupby("position_threshold_m").first()
    cells = [
        f"{row.localized_pct:.1f} ({row.localized_low_pct:.1f}–{row.localized_high_pct:.1f}), k={row.k}"
        for row in best_ewb.itertuples()
    ]
    assert ["toy", "approximation", "ewb", "netvlad", *cells] in best
    table = markdown_rows(tmp_path / "report" / "tables" / "localization_toy_global_sfm_pnp.md")
    assert table[0] == ["ranking", "k", "0.25 m, 2°", "5 m, 10°"]
    assert len(table) == 2 + 3 * len(KS)  # header, rule, a row per ranking and k
    assert (run / "results.csv").read_bytes() == tidy


def test_report_of_a_multirun_produces_every_figure_and_table(tmp_path):
    runs = tmp_path / "multirun"
    write_run(runs / "0_netvlad", ["netvlad"])
    write_run(runs / "1_apgem", ["apgem"])
    report = build_report([runs], tmp_path / "report")
    output = report.parent
    figures = {
        *(f"toy_{p}_{m}" for p, m in (("approximation", "ewb"), ("approximation", "csi"), ("global_sfm", "pnp"))),
        *(f"toy_{metric}_at_k" for metric in ("precision", "recall", "map")),
        *(f"toy_scatter_{metric}_{GROUNDTRUTH}" for metric in ("precision", "recall", "map")),
        *(f"toy_violin_{metric}_{GROUNDTRUTH}" for metric in ("precision", "recall", "average_precision")),
        "toy_subset_blurry",
    }
    written = {path.stem for path in (output / "figures").glob("*.png")}
    assert written == figures
    for stem in figures:
        assert (output / "figures" / f"{stem}.png").stat().st_size > 1000
        assert (output / "figures" / f"{stem}.pdf").stat().st_size > 1000
    text = report.read_text()
    for stem in figures:
        assert f"(figures/{stem}.png)" in text
    tables = (
        "table1_groundtruth_statistics",
        "table2_revisited",
        f"pearson_recall_{GROUNDTRUTH}",
        f"spearman_precision_{GROUNDTRUTH}",
        "median_errors",
    )
    for stem in tables:
        assert (output / "tables" / f"{stem}.tex").read_text().startswith("\\begin{table}")
        assert (output / "tables" / f"{stem}.md").is_file()
    assert "gt\\_relative\\_pose" in (output / "tables" / "table1_groundtruth_statistics.tex").read_text()
    assert (
        "## Median errors" in text
        and "median position error (m)" in (output / "tables" / "median_errors.md").read_text()
    )
    pearson = pd.read_csv(output / "correlation_dataset_pearson.csv")
    assert set(pearson["ranking"]) == {"apgem", "netvlad"}  # descriptors only, from both runs
    assert len(pd.read_csv(output / "correlation_query_pearson.csv.gz")) > 0
    assert "too few inliers" in text and "run time" in text
    # the two runs' descriptors compared with each other on the same queries, as within one run
    comparisons = pd.read_csv(output / "comparisons.csv")
    assert {("apgem", "netvlad"), ("apgem", GROUNDTRUTH), ("netvlad", "random")} <= set(
        zip(comparisons["ranking"], comparisons["other"])
    )


def test_figures_drawn_by_worker_processes_are_those_drawn_in_process(tmp_path):
    run = write_run(tmp_path / "run", ["netvlad", "apgem"])
    in_process = build_report([run], tmp_path / "here", figure_formats=["png"], figure_workers=1)
    by_workers = build_report([run], tmp_path / "workers", figure_formats=["png"], figure_workers=2)
    assert by_workers.read_text().replace("workers", "here") == in_process.read_text()
    sizes = {
        folder: {f.name: f.stat().st_size for f in (tmp_path / folder / "figures").glob("*.png")}
        for folder in ("here", "workers")
    }
    assert len(sizes["here"]) == 13 and sizes["workers"] == sizes["here"]  # the same figures, pixel for pixel in size


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


def test_runs_are_combined_without_repeating_ground_truth(tmp_path):
    first, second = write_run(tmp_path / "a", ["netvlad"]), write_run(tmp_path / "b", ["apgem"])
    single = load_runs([first])
    combined = load_runs([first, second])
    gt_rows = combined.results[combined.results["ranking"] == GROUNDTRUTH]
    assert len(gt_rows) == len(single.results[single.results["ranking"] == GROUNDTRUTH])
    assert set(combined.results["ranking"]) == {"netvlad", "apgem", GROUNDTRUTH, "random"}
    assert len(combined.query_errors) == len(single.query_errors) + len(load_runs([second]).query_errors) - len(
        single.query_errors[single.query_errors["ranking_kind"] != "descriptor"]
    )
    assert set(combined.revisited["ranking"]) == {"netvlad", "apgem"}


def _shift_results(run: Path, name: str) -> None:
    results = pd.read_csv(run / "results.csv")
    results.loc[results["ranking"] == name, "localized_pct"] += 1.0
    results.to_csv(run / "results.csv", index=False)


def test_one_descriptor_under_several_settings_is_labelled_by_its_overrides(tmp_path):
    runs = [write_run(tmp_path / "sweep" / str(i), ["netvlad"]) for i in range(2)]
    _shift_results(runs[1], "netvlad")
    for run, alpha in zip(runs, (4, 8)):
        (run / ".hydra").mkdir()
        (run / ".hydra" / "overrides.yaml").write_text(
            f"- model=netvlad\n- paradigms.approximation.weights.csi.alpha={alpha}\n"
        )
    combined = load_runs([tmp_path / "sweep"])
    variants = [
        "netvlad [paradigms.approximation.weights.csi.alpha=4]",
        "netvlad [paradigms.approximation.weights.csi.alpha=8]",
    ]
    assert set(combined.results["ranking"]) == {*variants, GROUNDTRUTH, "random"}
    assert set(combined.retrieval.loc[combined.retrieval["ranking_kind"] == "descriptor", "ranking"]) == set(variants)
    single = load_runs([runs[0]]).results
    first = combined.results[combined.results["ranking"] == variants[0]]
    assert len(first) == len(single[single["ranking"] == "netvlad"])
    assert len(combined.results[combined.results["ranking"] == GROUNDTRUTH]) == len(
        single[single["ranking"] == GROUNDTRUTH]
    )


def test_runs_without_overrides_are_labelled_by_directory_and_indistinguishable_runs_are_an_error(tmp_path):
    first, second = write_run(tmp_path / "a", ["netvlad"]), write_run(tmp_path / "b", ["netvlad"])
    _shift_results(second, "netvlad")
    assert {"netvlad [a]", "netvlad [b]"} <= set(load_runs([first, second]).results["ranking"])
    _shift_results(second, GROUNDTRUTH)  # e.g. a sweep over a ground-truth setting: both upper bounds stay
    rankings = set(load_runs([first, second]).results["ranking"])
    assert {f"{GROUNDTRUTH} [a]", f"{GROUNDTRUTH} [b]"} <= rankings and GROUNDTRUTH not in rankings
    third = write_run(tmp_path / "c" / "a", ["netvlad"])
    _shift_results(third, "netvlad")
    with pytest.raises(ValueError, match="netvlad"):
        load_runs([first, third])


def test_command_line_entry_point_with_only_a_localization_table(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    localization("netvlad", "descriptor")[0].to_csv(run / "results.csv", index=False)
    completed = subprocess.run(
        [sys.executable, "report.py", str(run)],
        cwd=Path(__file__).parents[2],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert completed.returncode == 0, completed.stderr
    stems = ("approximation_csi", "approximation_ewb", "global_sfm_pnp", "subset_blurry")
    expected = [f"toy_{stem}.{suffix}" for stem in stems for suffix in ("pdf", "png")]
    assert sorted(path.name for path in (run / "figures").iterdir()) == expected
    assert "## Localization" in (run / "report.md").read_text()


def test_headline_thresholds_and_retrieval_summary_values(tmp_path):
    from locretrieval.report.markdown import retrieval_summary
    from locretrieval.report.plots import headline_threshold

    run = write_run(tmp_path / "run", ["netvlad"])
    tables = load_runs([run])
    assert headline_threshold(tables.results, "approximation") == (5.0, 10.0)  # loosest, as Fig. 4
    assert headline_threshold(tables.results, "global_sfm") == (0.25, 2.0)  # tightest, as Figs. 5-6
    summary = retrieval_summary(tables.retrieval)
    row = tables.retrieval.query("subset == 'all' and ranking == 'netvlad' and metric == 'recall' and k == 5").iloc[0]
    # R@5 of the 6 queries, a share of them: Wilson's interval, as scipy gives it
    interval = stats.binomtest(round(6 * row["value"]), 6).proportion_ci(method="wilson")
    assert summary.loc[(row["dataset"], row["groundtruth"], "netvlad"), ("recall", 5)] == (
        f"{100 * row['value']:.1f} ({100 * interval.low:.1f}–{100 * interval.high:.1f})"
    )


def test_runs_written_before_k_effective_existed_read_it_as_k(tmp_path):
    run = write_run(tmp_path / "run", ["netvlad"])
    pd.read_csv(run / "results.csv").drop(columns="k_effective").to_csv(run / "results.csv", index=False)
    loaded = load_runs([run]).results
    assert len(loaded) and (loaded["k_effective"] == loaded["k"]).all()


def test_report_compares_every_two_rankings_and_says_where_a_paradigm_cannot_separate_them(tmp_path):
    run = write_run(tmp_path / "run", ["netvlad"])
    text = build_report([run], tmp_path / "report", figure_formats=[]).read_text()
    comparisons = pd.read_csv(tmp_path / "report" / "comparisons.csv")
    outcomes = pd.read_csv(run / "query_localized.csv.gz")
    row = comparisons.query(
        "paradigm == 'global_sfm' and k == 5 and position_threshold_m == 5.0 and ranking == 'netvlad' and "
        "other == 'random'"
    ).iloc[0]
    at = outcomes.query("paradigm == 'global_sfm' and k == 5 and position_threshold_m == 5.0")
    first = at[at["ranking"] == "netvlad"].set_index("query")["localized"]
    second = at[at["ranking"] == "random"].set_index("query")["localized"].loc[first.index]
    assert (row["only_ranking"], row["only_other"]) == (
        ((first == 1) & (second == 0)).sum(),
        ((first == 0) & (second == 1)).sum(),
    )
    assert row["difference_pts"] == pytest.approx(100 * (first.mean() - second.mean()))
    pairs = comparisons.query("paradigm == 'global_sfm' and k == 5 and position_threshold_m == 5.0")
    assert len(pairs) == 3  # netvlad, the ground truth and random: three pairs
    # 6 queries tell nothing apart: every verdict says so, and the report says which paradigms cannot separate
    assert set(comparisons["verdict"]) == {"not distinguishable"}
    assert "### Which differences are real" in text
    assert "**global_sfm at 5 m, 10° does not separate rankings on toy**" in text
    # one descriptor: no Spearman table over the descriptors, and why
    assert "Spearman's rho over the descriptors needs at least 2 descriptors; these runs have 1" in text
    assert not list((tmp_path / "report" / "tables").glob("spearman_*"))
    assert "nan" not in text.lower().replace("nanmean", "")


@pytest.mark.parametrize(
    "name",
    ["[a](javascript:alert(1))", "![i](http://x/i.png)", "[x]: http://e", "[a][x]", "&#91;x&#93; &amp;", "<b>x</b>"],
)
def test_markdown_text_is_shown_literally_and_forms_no_link_image_definition_or_tag(name):
    import html

    import markdown

    from locretrieval.report.markdown import md_link, md_text

    for line in (f"- **{md_text(name)}**: {md_text(name)}", md_text(name), md_link(name, "a b.png")):
        page = markdown.markdown(f"{line}\n\n[x] [a]", extensions=["tables"])  # [x]: what a definition would link
        tags = set(re.findall(r"<(\w+)", page))
        assert tags <= {"ul", "li", "strong", "p", "a"}, page
        assert page.count("<a ") == (line.startswith("[") and line.endswith("(a%20b.png)")), page  # md_link's only
        assert name in html.unescape(re.sub(r"<[^>]+>", "", page)), page  # shown as it is


def test_markdown_text_keeps_the_characters_that_form_nothing():
    from locretrieval.report.markdown import md_text

    assert md_text("approximation (k=[1, 2, 3, 5])") == "approximation (k=[1, 2, 3, 5])"
    assert md_text("R&D [blur] a_b") == "R&D [blur] a_b"
    assert (
        md_text("[a](b) [c]: d [e][f] <g> &#1; &amp;")
        == "[a&#93;(b) [c&#93;: d [e&#93;[f] &#60;g&#62; &#38;#1; &#38;amp;"
    )


def test_the_run_section_shows_a_list_of_k_as_written_in_markdown_and_html(tmp_path):
    import html
    import json

    run = write_run(tmp_path / "run", ["netvlad"])
    summary = {"paradigms": "approximation (k=[1, 2, 3, 5, 10])", "model": "R&D [blur] <b>x</b> [a](b)"}
    (run / "summary.json").write_text(json.dumps(summary))
    report = build_report([run], tmp_path / "report", figure_formats=[])  # the text only
    text = report.read_text()
    assert "- **paradigms**: approximation (k=[1, 2, 3, 5, 10])" in text  # the brackets as they are
    assert "&#91;" not in text and text.count("&#93;") == 1  # the one ] that would close a link: [a](b)
    page = report.with_suffix(".html").read_text()
    shown = html.unescape(re.sub(r"<[^>]+>", "", page))  # what a browser shows
    assert "paradigms: approximation (k=[1, 2, 3, 5, 10])" in shown
    assert "model: R&D [blur] <b>x</b> [a](b)" in shown and "<b>x</b>" not in page  # shown, not made markup


def test_a_report_page_wraps_long_words_and_scrolls_a_wide_table_inside_itself(tmp_path):
    """The page's style (measured in Chromium by tests/report/test_report_browser.py): text breaks
    anywhere it must (a Hydra job folder is one long word), a table is its own scrolling box."""
    from locretrieval.report.html import write_html

    page = tmp_path / "summary.md"
    page.write_text("# s\n\n| trial | gap |\n| --- | --- |\n| 0_blur_probability=0.489309171116382,b=1 | 1 |\n")
    style = re.search(r"<style>(.*?)</style>", write_html(page).read_text(), re.DOTALL).group(1)
    rules = {
        selector.strip(): {
            item.split(":")[0].strip(): item.split(":", 1)[1].strip() for item in body.split(";") if ":" in item
        }
        for selector, body in re.findall(r"([^{}]+)\{([^}]*)\}", style)
    }
    assert rules["body"]["overflow-wrap"] == "anywhere"
    assert rules["table"]["display"] == "block" and rules["table"]["overflow-x"] == "auto"
    assert rules["table"]["max-width"] == "100%"
