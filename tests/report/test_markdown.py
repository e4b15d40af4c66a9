"""The report's Markdown tables and headline figures (`locretrieval.report.markdown`)."""

import re

import pytest
from report_runs import KS, localization, write_run
from scipy import stats

from locretrieval.report.markdown import pivot_localization
from locretrieval.report.tables import load_runs


def test_pivot_localization_reads_the_table_with_k_as_rows_and_thresholds_as_columns():
    results, _, _ = localization("netvlad", "descriptor")
    pivot = pivot_localization(results, "global_sfm", "pnp")
    assert list(pivot.columns) == ["0.25 m, 2°", "5 m, 10°"] and list(pivot.index) == [("netvlad", k) for k in KS]
    row = results.set_index(["subset", "paradigm", "k", "position_threshold_m"]).loc[("all", "global_sfm", 5, 5.0)]
    # the share of the 6 queries with its Wilson interval, as scipy gives it
    interval = stats.binomtest(int(row["localized"]), 6).proportion_ci(method="wilson")
    expected = f"{row['localized_pct']:.1f} ({100 * interval.low:.1f}–{100 * interval.high:.1f})"
    assert pivot.loc[("netvlad", 5), "5 m, 10°"] == expected


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
