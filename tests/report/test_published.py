"""The published kapture-localization results shipped as CSV, and the report's comparison with them."""

import math
import tomllib
from fnmatch import fnmatch
from pathlib import Path

import pandas as pd
import pytest
from omegaconf import OmegaConf

from locretrieval.metrics.localization import RESULT_COLUMNS
from locretrieval.metrics.uncertainty import share_interval
from locretrieval.report import build_report
from locretrieval.report import published as published_module
from locretrieval.report.published import MATCH_KEYS, PUBLISHED_COLUMNS, PUBLISHED_DIR, load_published, parse_adoc

ROOT = Path(__file__).resolve().parents[2]

#: Values read by hand off kapture-localization's doc/benchmark_results_*.adoc (commit 916e9d8):
#: (dataset, local feature, global feature, paradigm, method, k, condition, metres, degrees) ->
#: (% localized, median metres, median degrees); NaN: no median published.
NAN = math.nan
READ_OFF = {
    ("aachen", "Feather2d2 20k", "AP-GeM-LM18", "global_sfm", "pnp", 1, "day", 0.25, 2.0): (80.2, NAN, NAN),
    ("aachen", "Feather2d2 20k", "AP-GeM-LM18", "global_sfm", "pnp", 1, "night", 5.0, 10.0): (78.0, NAN, NAN),
    ("aachen", "r2d2_WASF_N8_big 20k", "how", "local_sfm", "pnp", 3, "night", 0.25, 2.0): (35.1, NAN, NAN),
    ("aachen", "Feather2d2 20k", "r101delg_gldv2clean", "approximation", "ewb", 50, "night", 5.0, 10.0): (
        5.2,
        NAN,
        NAN,
    ),
    ("baidu", "r2d2_WASF_N8_big 20k", "fire", "global_sfm", "pnp", 2, "all", 0.5, 5.0): (75.31, 0.1798, 0.838),
    ("baidu", "Feather2d2 20k", "DELG", "local_sfm", "pnp", 1, "all", 5.0, 10.0): (0.0, math.inf, math.inf),
    ("baidu", "Feather2d2 20k", "how", "approximation", "ewb", 10, "all", 5.0, 10.0): (8.90, 8.7749, 23.7837),
    ("gangnam", "Feather2d2 20k", "openibl_vgg16_netvlad", "approximation", "ewb", 2, "validation", 5.0, 10.0): (
        12.99,
        20.0063,
        29.2547,
    ),
    ("gangnam", "Feather2d2 20k", "openibl_vgg16_netvlad", "approximation", "ewb", 2, "test", 5.0, 10.0): (
        9.4,
        NAN,
        NAN,
    ),
    ("gangnam", "r2d2_WASF_N8_big 20k", "r101delg_gldv2clean", "global_sfm", "pnp", 50, "test", 1.0, 5.0): (
        71.1,
        NAN,
        NAN,
    ),
    ("gangnam", "r2d2_WASF_N8_big 20k", "fire", "local_sfm", "pnp", 20, "validation", 0.1, 1.0): (
        29.48,
        0.2289,
        2.1484,
    ),
    ("robotcar", "r2d2_WASF_N8_big 20k", "netvlad_vd16pitts", "approximation", "ewb", 20, "night", 5.0, 10.0): (
        0.2,
        NAN,
        NAN,
    ),
    ("robotcar", "Feather2d2 20k", "densevlad_multi", "local_sfm", "pnp", 50, "day", 0.5, 5.0): (78.1, NAN, NAN),
}
#: Rows per CSV: features x k x conditions x thresholds of each table, summed by hand.
ROWS = {"aachen": 1300, "baidu": 692, "gangnam": 1300, "robotcar": 1400}


def test_shipped_tables_hold_the_values_of_the_source():
    table = load_published(PUBLISHED_DIR)
    assert list(table.columns) == PUBLISHED_COLUMNS
    assert table.groupby("dataset").size().to_dict() == ROWS
    assert not table.duplicated(MATCH_KEYS).any()
    indexed = table.set_index(MATCH_KEYS)
    for key, (localized, median_m, median_deg) in READ_OFF.items():
        row = indexed.loc[key]
        assert row["localized_pct"] == pytest.approx(localized), key
        for value, expected in (
            (row["median_position_error_m"], median_m),
            (row["median_rotation_error_deg"], median_deg),
        ):
            assert (math.isnan(value) and math.isnan(expected)) or value == pytest.approx(expected), key


def test_the_tables_are_package_data():
    package_data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"][
        "locretrieval.report"
    ]
    shipped = [path.relative_to(PUBLISHED_DIR.parent).as_posix() for path in PUBLISHED_DIR.iterdir()]
    assert sorted(shipped) == sorted(["published/SOURCES.md", *(f"published/{d}.csv" for d in ROWS)])
    assert all(any(fnmatch(path, pattern) for pattern in package_data) for path in shipped)
    sources = (PUBLISHED_DIR / "SOURCES.md").read_text()
    assert "916e9d854fbc2a7fdb7adf071510a1d0e69a5293" in sources and all(
        f"benchmark_results_{d}.adoc" in sources for d in ROWS
    )


def test_adoc_tables_with_conditions_medians_and_spans_are_parsed():
    text = "\n".join([
        "== Feather2d2 20k Results", "=== EWB", "[%header]", "|===",
        "|feature type|topk|test 3+|validation",
        "|||(5.0m_10.0deg)|(5.0m_10.0deg)|median distance (m)|median angle (deg)",
        "|fire|1      |11.8%|11.35%|1.1299|24.3258", "||||||", "|===",
        "=== global_sfm", "[%header,format=csv,separator=;]", "|===",
        "feature type;top;(0.25, 2.0);median distance (m);median angle (deg)", "how;3 ;60.78%;inf;inf", "|===",
    ])  # fmt: skip
    table = parse_adoc(text, "gangnam", "x.adoc").set_index(["paradigm", "condition"])
    assert len(table) == 3
    test, validation = table.loc[("approximation", "test")], table.loc[("approximation", "validation")]
    assert (test["localized_pct"], test["k"], test["global_feature"]) == (11.8, 1, "fire") and math.isnan(
        test["median_position_error_m"]
    )
    assert (
        validation["localized_pct"],
        validation["median_position_error_m"],
        validation["median_rotation_error_deg"],
    ) == (11.35, 1.1299, 24.3258)
    csv = table.loc[("global_sfm", "all")]
    assert (csv["localized_pct"], csv["position_threshold_m"], csv["median_position_error_m"]) == (
        60.78,
        0.25,
        math.inf,
    )


def test_malformed_tables_are_errors_naming_the_file(tmp_path):
    header = ["== r2d2 Results", "=== EWB", "[%header]", "|==="]
    with pytest.raises(ValueError, match=r"bad\.adoc.*4 labels"):
        parse_adoc(
            "\n".join([*header, "|feature type|topk|day 3+|night", "|||(5.0, 10.0)|(5.0, 10.0)", "|==="]),
            "x",
            "bad.adoc",
        )
    with pytest.raises(ValueError, match=r"bad\.adoc.*'12,5%' is not a number"):
        parse_adoc(
            "\n".join([*header, "|feature type|topk|day", "|||(5.0, 10.0)", "|fire|1|12,5%", "|==="]), "x", "bad.adoc"
        )
    with pytest.raises(ValueError, match=r"bad\.adoc: no benchmark table"):
        parse_adoc("= nothing here", "x", "bad.adoc")
    (tmp_path / "x.csv").write_text("dataset,k\nbaidu,1\n")
    with pytest.raises(ValueError, match=r"x\.csv: missing columns"):
        load_published(tmp_path)


def write_run(directory: Path, dataset: str, rows: list[tuple], features: dict) -> Path:
    """A finished run: ``results.csv`` with ``rows`` of (subset, ranking, paradigm, method, k,
    metres, degrees, % localized) of 100 queries and a ``config.yaml`` whose ``sfm.features`` are ``features``."""
    directory.mkdir(parents=True)
    results = []
    for s, r, p, m, k, x, y, pct in rows:
        low, high = share_interval(round(pct), 100, 0.95)
        results.append(
            (dataset, s, r, "descriptor", p, m, k, k, x, y, pct, 100, round(pct), 100 * low, 100 * high, "m")
        )
    pd.DataFrame(results, columns=RESULT_COLUMNS).to_csv(directory / "results.csv", index=False)
    OmegaConf.save(OmegaConf.create({"sfm": {"features": features}}), directory / "config.yaml")
    return directory


def published_folder(directory: Path, rows: list[dict]) -> Path:
    directory.mkdir()
    defaults = {"median_position_error_m": math.nan, "median_rotation_error_deg": math.nan}
    pd.DataFrame([{**defaults, **row} for row in rows], columns=PUBLISHED_COLUMNS).to_csv(
        directory / "robotcar.csv", index=False
    )
    return directory


R2D2 = {
    "_target_": "locretrieval.sfm.features.KaptureFeatures",
    "name": "r2d2_WASF-N8_20k",
    "max_keypoints": None,
}
PUBLISHED_ROW = {
    "dataset": "robotcar", "local_feature": "r2d2_WASF_N8_big 20k", "global_feature": "netvlad_vd16pitts",
    "paradigm": "global_sfm", "method": "pnp", "k": 5, "condition": "night",
    "position_threshold_m": 0.25, "rotation_threshold_deg": 2.0, "localized_pct": 14.5,
}  # fmt: skip


def published_section_text(report: Path) -> str:
    """The text of ``report.md``'s published-results section, below its heading."""
    return report.read_text().split("## Published results (kapture-localization)\n")[1].split("\n## ")[0]


def comparison_rows(report: Path) -> list[list[str]]:
    """The cells of the markdown comparison table's rows, from ``report.md``."""
    section = published_section_text(report)
    return [
        [cell.strip() for cell in line.strip("|").split("|")]
        for line in section.splitlines()
        if line.startswith("|") and "netvlad" in line
    ]


def test_the_report_shows_the_published_value_and_the_difference(tmp_path, monkeypatch):
    ours = [("night", "netvlad", "global_sfm", "pnp", 5, 0.25, 2.0, 20.0),
            ("night", "netvlad", "global_sfm", "pnp", 5, 5.0, 10.0, 61.25),  # no published threshold (5 m, 10°)
            ("day", "netvlad", "global_sfm", "pnp", 5, 0.25, 2.0, 50.0)]  # fmt: skip
    run = write_run(tmp_path / "run", "robotcar", ours, R2D2)
    other = {**PUBLISHED_ROW, "local_feature": "Feather2d2 20k", "localized_pct": 99.0}  # other local features
    monkeypatch.setattr(
        published_module, "PUBLISHED_DIR", published_folder(tmp_path / "published", [PUBLISHED_ROW, other])
    )
    report = build_report([run], run, figure_formats=[])
    rows = comparison_rows(report)
    assert len(rows) == 1, rows
    cells = rows[0]
    assert cells[:8] == [
        "robotcar",
        "night",
        "r2d2_WASF_N8_big 20k",
        "netvlad (netvlad_vd16pitts)",
        "global_sfm",
        "pnp",
        "5",
        "0.25 m, 2°",
    ]
    assert [float(cell) for cell in cells[8:11]] == [20.0, 14.5, pytest.approx(20.0 - 14.5)]
    assert (run / "tables" / "published_comparison.tex").is_file()


@pytest.mark.parametrize(
    ("features", "described"),
    [({"_target_": "locretrieval.sfm.features.SiftFeatures"}, "local features sift;"),
     ({**R2D2, "max_keypoints": 5000}, "local features kapture r2d2_WASF-N8_20k (best 5000);"),  # not the published 20k
     ({"type": "kapture", "kapture": {"name": "r2d2_WASF-N8_20k"}, "max_keypoints": 5000},  # a run of 0.10 or earlier
      "local features kapture r2d2_WASF-N8_20k (best 5000);")],
)  # fmt: skip
def test_when_nothing_matches_one_line_says_what_was_looked_for(tmp_path, monkeypatch, features, described):
    run = write_run(
        tmp_path / "run", "robotcar", [("night", "netvlad", "global_sfm", "pnp", 5, 0.25, 2.0, 20.0)], features
    )
    monkeypatch.setattr(published_module, "PUBLISHED_DIR", published_folder(tmp_path / "published", [PUBLISHED_ROW]))
    section = published_section_text(build_report([run], run, figure_formats=[]))
    lines = [line for line in section.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("No published result matches this run: looked for dataset robotcar;")
    assert "global features netvlad (as netvlad_vd16pitts);" in lines[0] and described in lines[0]
    assert "paradigms global_sfm/pnp" in lines[0] and "(published: robotcar)" in lines[0]
