"""The tidy tables of finished runs read back and combined (`locretrieval.report.tables`)."""

from pathlib import Path

import pandas as pd
import pytest
from report_runs import GROUNDTRUTH, write_run

from locretrieval.report.tables import load_runs


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


def test_runs_written_before_k_effective_existed_read_it_as_k(tmp_path):
    run = write_run(tmp_path / "run", ["netvlad"])
    pd.read_csv(run / "results.csv").drop(columns="k_effective").to_csv(run / "results.csv", index=False)
    loaded = load_runs([run]).results
    assert len(loaded) and (loaded["k_effective"] == loaded["k"]).all()
