"""The summary of train.py runs (`locretrieval.report.training_summary`): the best marked, the gap of the
means, the held-out figures and whether the best is distinguishable from the next."""

import math
import re

import pandas as pd
import pytest
from omegaconf import OmegaConf
from scipy import stats
from training_runs import METRIC, gap_run

from locretrieval.report.training_summary import write_summary


def test_the_summary_of_runs_marks_the_best_closes_the_gap_of_the_means_and_says_why_a_gap_is_undefined(tmp_path):
    p1, sfm = "approximation/ewb/k3/5m_10deg", "global_sfm/pnp/k5/0.25m_2deg"
    runs = [
        gap_run(tmp_path, "a", 40.0, [(p1, 10.0, 40.0, 20.0, 60.0), (sfm, 50.0, 55.0, 50.0, 50.0)]),
        gap_run(tmp_path, "b", 20.0, [(p1, 10.0, 20.0, 20.0, 30.0), (sfm, 50.0, 60.0, 40.0, 70.0)]),
    ]
    unfinished = tmp_path / "c"
    (unfinished / ".hydra").mkdir(parents=True)
    pd.DataFrame({"epoch": [-1], "metric": [METRIC], "value": [1.0]}).to_csv(unfinished / "validation.csv", index=False)
    OmegaConf.save(OmegaConf.create(["seed=c", "debug=quick"]), unfinished / ".hydra" / "overrides.yaml")
    markdown = write_summary([*runs, unfinished], tmp_path / "out").read_text()
    lines = {line.split("|")[1].strip(): line for line in markdown.splitlines() if line.startswith("| ")}
    # (40 - 20) / (60 - 20) of 100 queries, with its paired bootstrap interval
    assert re.search(r"20\.0 / 10\.0 / 40\.0 / 60\.0 \(50 % \(\d+ to \d+\)\)", lines["a (best)"])
    assert (
        "50.0 / 50.0 / 55.0 / 50.0 (no gap to close: the ground truth (50.0 %) is not distinguishable from "
        "densevlad (50.0 %) on these 100 queries)" in lines["a (best)"]
    )
    # 10 points of 100 queries, each localized by the ground truth only: a gap, of which nothing was closed
    assert "20.0 / 10.0 / 20.0 / 30.0 (0 %" in lines["b"] and "40.0 / 50.0 / 60.0 / 70.0 (67 %" in lines["b"]
    # the gap of the means, not the mean of 50 % and 0 %, where every run has a gap
    assert (
        "20.0 / 10.0 / 30.0 / 45.0 (gap of the means 40 %; no interval: the runs' queries differ)" in lines["mean of 2"]
    )
    assert "45.0 / 50.0 / 57.5 / 60.0 (no gap of the means: 1 of 2 runs have no gap to close)" in lines["mean of 2"]
    assert "no summary.json: it did not finish" in lines["c"] and "seed=c" in lines["c"]
    # the objective with its interval of 100 queries, and no held-out figure without held-out queries
    interval = stats.binomtest(40, 100).proportion_ci(method="wilson")
    assert f"40.0 ({100 * interval.low:.1f}–{100 * interval.high:.1f}), 100 queries, epoch 1" in lines["a (best)"]
    assert "no held-out queries" in lines["a (best)"]
    assert not re.search(r"\bnan\b|\binf\b", markdown, re.IGNORECASE)
    table = pd.read_csv(tmp_path / "out" / "summary.csv")
    assert table["best"].tolist() == [True, False, False] and table["objective"].tolist()[:2] == [40.0, 20.0]
    assert table.loc[0, "objective_low"] == pytest.approx(100 * interval.low)
    assert math.isnan(table.loc[0, f"{sfm} gap_closed_pct"]) and table.loc[0, f"{sfm} why"].startswith(
        "no gap to close"
    )
    assert (tmp_path / "out" / "summary.html").read_text().count("<tr>") == 5  # header, 3 trials, the mean


def test_the_summary_reports_the_held_out_figures_and_whether_the_best_trial_beats_the_next(tmp_path):
    p1 = "approximation/ewb/k3/5m_10deg"
    best = gap_run(tmp_path, "a", 60.0, [(p1, 10.0, 40.0, 20.0, 60.0)], queries=50, held_out=56.0)
    runner = gap_run(tmp_path, "b", 50.0, [(p1, 10.0, 40.0, 20.0, 60.0)], queries=50, held_out=50.0)
    markdown = write_summary([best, runner], tmp_path / "out").read_text()
    # held out: 28 and 25 of 50 queries, nested, so 3 queries discordant, all the best trial's
    p_value = stats.binomtest(3, 3, 0.5).pvalue
    assert (
        "trial a against the next, trial b, on the 50 held-out queries: +6.0 (" in markdown
        and f"(exact McNemar p={p_value:.2g}): not distinguishable" in markdown
    )
    interval = stats.binomtest(28, 50).proportion_ci(method="wilson")
    assert f"56.0 ({100 * interval.low:.1f}–{100 * interval.high:.1f}), 50 queries" in markdown
    table = pd.read_csv(tmp_path / "out" / "summary.csv").set_index("trial")
    assert table.loc["a", ["held_out", "held_out_queries", "objective_epoch"]].tolist() == [56.0, 50, 1]
