"""Retrieval galleries: the image of a gallery, cached thumbnails, which queries are shown, and
the report's gallery section and HTML page built from a run folder."""

import re

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf
from PIL import Image
from report_runs import (
    HEIGHT,
    KS,
    NUM_QUERIES,
    WIDTH,
    gallery_run,
    palette,
    ranking,
    relevance,
    solid_images,
    write_run,
)

import locretrieval.report.gallery as gallery
from locretrieval.build import build_report_gallery
from locretrieval.config import ConfigError, validated
from locretrieval.report import build_report
from locretrieval.report.gallery import (
    BORDER,
    NOT_RELEVANT,
    QUERY,
    QUERY_GAP,
    RELEVANT,
    SPACING,
    GallerySettings,
    Thumbnails,
    gallery_image,
    representative_k,
    select_queries,
)
from locretrieval.report.html import write_html
from locretrieval.retrieval import EMPTY


def nearest(pixel: np.ndarray, colours: list[tuple[int, int, int]]) -> int:
    return int(np.argmin(np.abs(np.asarray(colours, dtype=float) - pixel).sum(axis=1)))


def tile_origin(row: int, slot: int, tile: tuple[int, int]) -> tuple[int, int]:
    """Top-left pixel of a tile: ``slot`` -1 is the query, 0.. the ranked images."""
    height, width = tile
    x = 0 if slot < 0 else width + QUERY_GAP + slot * (width + SPACING)
    return row * (height + SPACING), x


def test_gallery_image_shows_each_query_then_its_ranked_images_framed_by_relevance(tmp_path):
    database_colours, query_colours = palette(6), palette(2, offset=6)
    database = solid_images(tmp_path / "db", database_colours, [f"d{i}.png" for i in range(6)])
    queries = solid_images(tmp_path / "q", query_colours, ["q0.png", "q1.png"])
    indices = np.array([[3, 1, 5], [0, 2, EMPTY]])
    relevant = np.array([[True, False, True], [False, True, False]])
    image = gallery_image(queries, database, indices, relevant, Thumbnails(20))
    tile = (15 + 2 * BORDER, 20 + 2 * BORDER)  # 40x30 shrunk to 20x15, framed
    assert image.dtype == np.uint8 and image.shape == (
        2 * tile[0] + SPACING,
        tile[1] + QUERY_GAP + 3 * tile[1] + 2 * SPACING,
        3,
    )
    for row in range(2):
        top, left = tile_origin(row, -1, tile)
        assert tuple(image[top, left]) == QUERY
        assert nearest(image[top + tile[0] // 2, left + tile[1] // 2], query_colours) == row
        for slot in range(3):
            top, left = tile_origin(row, slot, tile)
            if indices[row, slot] == EMPTY:
                assert (image[top : top + tile[0], left : left + tile[1]] == 255).all()  # blank
                continue
            assert tuple(image[top, left]) == (RELEVANT if relevant[row, slot] else NOT_RELEVANT)
            assert nearest(image[top + tile[0] // 2, left + tile[1] // 2], database_colours) == indices[row, slot]


def test_gallery_image_refuses_masks_of_another_shape(tmp_path):
    paths = solid_images(tmp_path, palette(2), ["a.png", "b.png"])
    with pytest.raises(ValueError, match=r"must both be \[1, K\]"):
        gallery_image(paths[:1], paths, np.array([[0, 1]]), np.array([[True]]))


def test_thumbnails_are_made_once_and_remade_when_the_file_changes(tmp_path, monkeypatch):
    path = tmp_path / "big.jpg"
    Image.new("RGB", (1600, 1200), (200, 40, 40)).save(path, quality=90)
    first = Thumbnails(160, tmp_path / "cache")(path)
    assert first.shape == (120, 160, 3) and len(list((tmp_path / "cache").glob("*.npy"))) == 1
    monkeypatch.setattr(gallery, "read_image", lambda *args, **kwargs: pytest.fail("the cached thumbnail was not used"))
    np.testing.assert_array_equal(Thumbnails(160, tmp_path / "cache")(path), first)
    monkeypatch.undo()
    Image.new("RGB", (800, 1600), (10, 200, 10)).save(path, quality=90)  # new size and time: a new key
    assert Thumbnails(160, tmp_path / "cache")(path).shape == (160, 80, 3)
    assert Thumbnails(64, tmp_path / "cache")(path).shape == (64, 32, 3)
    assert len(list((tmp_path / "cache").glob("*.npy"))) == 3


def test_representative_k_is_the_largest_k_whose_images_are_shown():
    assert representative_k([1, 2, 5, 10], 5) == 5
    assert representative_k([1, 2, 5, 10], 3) == 2
    assert representative_k([10, 20], 5) == 10


def settings(**values) -> GallerySettings:
    defaults = {"queries": "selected", "k": 3, "worst": 2, "random": 2, "seed": 0, "thumbnail_size": 160}
    return validated(GallerySettings, {**defaults, **values}, "report.gallery")


def test_gallery_settings_name_the_key_they_refuse():
    with pytest.raises(ConfigError, match=r"report.gallery.queries: must be 'selected' or 'all'"):
        settings(queries="worst")


def expected_worst(errors: pd.DataFrame, k: int, count: int) -> list[str]:
    """The worst queries of one ranking, computed here with pandas from the per-query errors."""
    rows = errors[errors["k"] == k].copy()
    normalised = np.maximum(rows["position_error_m"] / 5.0, rows["rotation_error_deg"] / 10.0)
    rows["score"] = np.minimum(normalised.fillna(1.0), 1.0)
    scores = rows.groupby("query")["score"].mean().reset_index()
    return list(scores.sort_values(["score", "query"], ascending=[False, True])["query"].head(count))


def test_worst_queries_are_the_largest_mean_capped_errors_and_random_ones_are_seeded(tmp_path):
    run = write_run(tmp_path / "run", ["netvlad"])
    errors = pd.read_csv(
        run / "query_errors.csv.gz",
        keep_default_na=False,
        na_values={"position_error_m": [""], "rotation_error_deg": [""]},
    )
    errors = errors[errors["ranking"] == "netvlad"]
    names = [f"q{i}.png" for i in range(NUM_QUERIES)]
    scores = gallery.query_scores(gallery.at_representative_k(errors, 3), (5.0, 10.0))
    chosen = select_queries(names, scores, settings(worst=3, random=2))
    worst = [names[q] for q, why in chosen if why.startswith("worst")]
    assert worst == expected_worst(errors, max(k for k in KS if k <= 3), 3)  # k=2: KS has no 3
    assert [why for _, why in chosen] == ["worst 1", "worst 2", "worst 3", "random", "random"]
    drawn = [q for q, why in chosen if why == "random"]
    assert not set(drawn) & {names.index(n) for n in worst} and drawn == sorted(drawn)
    assert select_queries(names, scores, settings(worst=3, random=2)) == chosen
    other_seeds = {
        tuple(q for q, why in select_queries(names, scores, settings(worst=0, random=2, seed=s))) for s in range(8)
    }
    assert len(other_seeds) > 1
    assert select_queries(names, scores, settings(queries="all")) == [(q, "") for q in range(NUM_QUERIES)]


def gallery_rows(report: str) -> list[list[str]]:
    section = report[report.index("### Gallery: netvlad") :].split("\n\n")[1]
    return [[cell.strip() for cell in re.split(r"(?<!\\)\|", line)[1:-1]] for line in section.splitlines()[2:]]


def test_report_gallery_marks_the_ground_truth_relevance_and_shows_each_outcome(tmp_path):
    run, database_colours, query_colours = gallery_run(tmp_path)
    output = tmp_path / "report"
    report = build_report(
        [run],
        output,
        figure_formats=[],
        gallery=settings(worst=2, random=2),
        thumbnail_cache=tmp_path / "thumbs",
        image_roots=[tmp_path / "images"],
    )
    rows = gallery_rows(report.read_text())
    errors = pd.read_csv(
        run / "query_errors.csv.gz",
        keep_default_na=False,
        na_values={"position_error_m": [""], "rotation_error_deg": [""]},
    )
    netvlad = errors[errors["ranking"] == "netvlad"]
    assert [row[0].strip("`") for row in rows[:2]] == expected_worst(netvlad, 2, 2)
    assert [row[1] for row in rows] == ["worst 1", "worst 2", "random", "random"]
    indices, relevant = ranking("netvlad", "descriptor").indices, relevance().toarray()
    tile = (HEIGHT + 2 * BORDER, WIDTH + 2 * BORDER)
    for number, row in enumerate(rows):
        q = int(row[0].strip("`")[1:-4])
        file = re.search(r"\]\((galleries/netvlad/\d+\.jpg)\)", row[2]).group(1)
        image = np.asarray(Image.open(output / file), dtype=float)
        assert nearest(image[tile[0] // 2, tile[1] // 2], query_colours) == q
        for slot in range(3):
            top, left = tile_origin(0, slot, tile)
            assert nearest(image[top + tile[0] // 2, left + tile[1] // 2], database_colours) == indices[q, slot]
            red, green, _ = image[top + tile[0] // 2, left : left + BORDER].mean(axis=0)
            assert (green > red + 80) if relevant[q, indices[q, slot]] else (red > green + 80), (q, slot)
        assert row[3] == f"{relevant[q, indices[q, :3]].sum()}/3"
        first = netvlad[(netvlad["query"] == f"q{q}.png") & (netvlad["k"] == 2)].iloc[0]
        outcome = (
            f"failed ({first['failure']})"
            if first["failure"]
            else f"{first['position_error_m']:.2f} m, {first['rotation_error_deg']:.1f}°"
        )
        assert row[4].startswith(f"{first['paradigm']} {first['method']} k=2: {outcome}")
        assert row[4].count("<br>") == len(netvlad[(netvlad["query"] == f"q{q}.png") & (netvlad["k"] == 2)]) - 1
    html = (output / "report.html").read_text()
    assert all(f'src="galleries/netvlad/{n:04d}.jpg"' in html for n in range(4))
    assert len(list((output / "galleries" / "netvlad").glob("*.jpg"))) == 4


def test_every_query_is_drawn_with_queries_all_and_a_rebuilt_report_drops_stale_rows(tmp_path):
    run, _, _ = gallery_run(tmp_path)
    output = tmp_path / "report"
    build_report([run], output, figure_formats=[], gallery=settings(queries="all"), image_roots=[tmp_path])
    assert len(gallery_rows((output / "report.md").read_text())) == NUM_QUERIES
    build_report([run], output, figure_formats=[], gallery=settings(worst=1, random=0), image_roots=[tmp_path])
    assert len(gallery_rows((output / "report.md").read_text())) == 1
    assert len(list((output / "galleries" / "netvlad").glob("*.jpg"))) == 1


def test_a_run_without_gallery_inputs_says_so(tmp_path):
    run = write_run(tmp_path / "run", ["netvlad"])
    text = build_report([run], tmp_path / "report", figure_formats=[], gallery=settings()).read_text()
    assert f"No galleries for `{run}` (no images.csv" in text


def test_html_report_links_its_files_relatively_and_the_3d_view_when_present(tmp_path):
    page = tmp_path / "report.md"
    page.write_text("# toy report\n\n| a | b |\n| --- | --- |\n| 1 | ![x](figures/x.png) |\n")
    html = write_html(page).read_text()
    assert "<title>toy report</title>" in html and '<img alt="x" src="figures/x.png"' in html and "<table>" in html
    assert "scene_3d.html" not in html and 'href="report.md"' in html
    (tmp_path / "scene_3d.html").write_text("<html></html>")
    assert '<a href="scene_3d.html">' in write_html(page).read_text()


def test_report_py_reads_a_runs_gallery_settings_with_overrides(tmp_path):
    section = {"queries": "selected", "k": 5, "worst": 10, "random": 5, "seed": 0, "thumbnail_size": 160}
    OmegaConf.save(
        {"paths": {"cache_dir": str(tmp_path / "cache")}, "report": {"gallery": section}}, tmp_path / "config.yaml"
    )
    assert build_report_gallery(tmp_path, ["queries=all", "k=10"]) == settings(**{**section, "queries": "all", "k": 10})
    with pytest.raises(ConfigError, match="report.gallery.k: must be >= 1"):
        build_report_gallery(tmp_path, ["k=0"])
    OmegaConf.save({"report": {"figure_formats": ["png"]}}, tmp_path / "config.yaml")  # a run of an earlier version
    assert build_report_gallery(tmp_path) is None
