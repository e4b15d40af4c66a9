"""The report of finished runs (`locretrieval.report.build`): its tables and figures from the tidy
tables, of one run or a multirun, drawn by worker processes, and report.py's command line."""

import re
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from report_runs import GROUNDTRUTH, KS, localization, write_run

from locretrieval.report import build_report


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
