"""Retrieval galleries: per query, what a ranking returned, marked relevant or not.

A gallery row is a query's thumbnail (framed blue) followed by the thumbnails of its top-k
database images, rank 1 first, each framed green when it is relevant under the ground truth, red
when it is not and grey when no relevance is known; a slot beyond the ranking's depth is blank.
`gallery_image` draws rows from image paths and arrays in memory (training logs it);
`gallery_section` writes the report's galleries from run folders.

Beside its tables, a run folder holds what galleries need (`write_gallery_inputs`, called by
``evaluate.py``): ``images.csv`` (columns ``set`` = database | query, ``index``, ``name``,
``path``: every image file, absolute) and ``relevance/<ground truth>.npz`` (each ground truth's
boolean ``[Q, N]`` relevance as the retrieval metrics count it: CSR arrays ``indptr``,
``indices``, ``shape``); the rankings are ``rankings/<name>.npz`` (``indices [Q, K]``, ``kind``,
``name``). File names are the names' `safe_name`.

Queries shown (``report.gallery``): with ``queries: selected``, per descriptor ranking, its
``worst`` queries and ``random`` others drawn with ``seed``; with ``queries: all``, every query,
in the scene's order. The worst have the largest score: the mean over the ranking's paradigms and
methods, each at its `representative_k`, of the capped pose error at the loosest threshold
(`capped_pose_error`: 1 when the query failed or missed the threshold); ties go by query name.
Queries estimated without a reference pose have no score (they may still be drawn at random).
"""

from __future__ import annotations

import functools
import logging
import os
import shutil
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from PIL import Image
from scipy import sparse

from locretrieval.bounded_files import check_npy
from locretrieval.cache import atomic_path, config_key, file_signature, load_arrays, safe_name, save_arrays
from locretrieval.config import require
from locretrieval.errors import DELETE_CACHE_FILE, DataFileError
from locretrieval.metrics.correlation import capped_pose_error
from locretrieval.report.markdown import ReportWriter, md_code, md_text
from locretrieval.report.plots import threshold_label
from locretrieval.report.run_files import RERUN, outside_roots, run_file
from locretrieval.report.tables import TABLES, read_table
from locretrieval.retrieval import EMPTY, relevant_hits
from locretrieval.scene import Scene
from locretrieval.scene.images import read_image
from locretrieval.scene.types import METRES

log = logging.getLogger(__name__)

IMAGES_FILE = "images.csv"
RELEVANCE_FOLDER = "relevance"
RANKINGS_FOLDER = "rankings"
#: The report's gallery images, below its folder (replaced at every report).
GALLERY_FOLDER = "galleries"
#: Frame colours (RGB): relevant, not relevant, unknown relevance, the query.
RELEVANT, NOT_RELEVANT, UNKNOWN, QUERY = (22, 163, 74), (220, 38, 38), (150, 150, 150), (37, 99, 235)
BACKGROUND = 255  # white
BORDER = 4  # pixels of frame around a thumbnail
SPACING = 3  # pixels between two thumbnails, and between two rows
QUERY_GAP = 16  # pixels between the query and its top-k
JPEG_QUALITY = 85


@dataclass
class GallerySettings:
    """The ``report.gallery`` config section (see the module docstring): ``queries`` (``selected``
    or ``all``), ``k`` database images per query, ``worst`` and ``random`` queries per ranking
    (``selected``), ``seed`` of the random draw, ``thumbnail_size`` (pixels, longer side)."""

    queries: str
    k: int
    worst: int
    random: int
    seed: int
    thumbnail_size: int

    def __post_init__(self) -> None:
        require(self.queries in ("selected", "all"), "queries", f"must be 'selected' or 'all', got {self.queries!r}")
        require(self.k >= 1, "k", f"must be >= 1, got {self.k}")
        require(
            self.worst >= 0 and self.random >= 0,
            "worst",
            f"worst and random must be >= 0, got {self.worst}, {self.random}",
        )
        require(self.thumbnail_size >= 8, "thumbnail_size", f"must be >= 8 pixels, got {self.thumbnail_size}")


class Thumbnails:
    """Thumbnails of image files (``uint8 [h, w, 3]``, at most ``size`` pixels on the longer side),
    each made once: cached as ``<cache_dir>/<key>.npy``, the key hashing the file's absolute path,
    size and modification time and ``size`` (written atomically; ``cache_dir=None``: not on disk),
    and the last ``memory`` ones kept in memory."""

    def __init__(self, size: int, cache_dir: str | os.PathLike | None = None, memory: int = 1024) -> None:
        self.size = size
        self.cache_dir = Path(cache_dir) if cache_dir is not None else None
        self._load = functools.lru_cache(maxsize=memory)(self._load_uncached)

    def __call__(self, path: str | os.PathLike) -> np.ndarray:
        return self._load(os.path.abspath(path))

    def _load_uncached(self, path: str) -> np.ndarray:
        if self.cache_dir is None:
            return read_image(path, max_side=self.size)
        file = self.cache_dir / f"{config_key(path, file_signature(path), self.size)}.npy"
        if file.is_file():
            check_npy(file, DELETE_CACHE_FILE)  # numpy allocates what the header declares before reading
            try:
                return np.load(file, allow_pickle=False)
            except (OSError, EOFError, ValueError) as error:
                raise DataFileError(file, f"not a readable thumbnail ({error})", DELETE_CACHE_FILE) from None
        thumbnail = read_image(path, max_side=self.size)
        with atomic_path(file) as temporary:
            np.save(temporary, thumbnail)
        return thumbnail


def gallery_image(
    query_paths: Sequence[str | os.PathLike],
    database_paths: Sequence[str | os.PathLike],
    indices: np.ndarray,
    relevant: np.ndarray | None = None,
    thumbnails: Thumbnails | None = None,
) -> np.ndarray:
    """The gallery of ``len(query_paths)`` queries as one ``uint8 [H, W, 3]`` RGB image: a row per
    query, its thumbnail then those of ``indices [Q, K]`` (rows into ``database_paths``, best
    first, ``EMPTY`` for none), framed by ``relevant [Q, K]`` (bool; ``None``: grey frames).
    Every thumbnail sits centred in a cell as large as the largest one (``thumbnails``: default
    160 pixels, not cached on disk)."""
    indices = np.asarray(indices)
    if indices.shape[0] != len(query_paths) or (relevant is not None and np.shape(relevant) != indices.shape):
        raise ValueError(
            f"gallery of {len(query_paths)} queries: indices {indices.shape} and relevant "
            f"{np.shape(relevant) if relevant is not None else None} must both be [{len(query_paths)}, K]"
        )
    thumbnails = thumbnails or Thumbnails(160)
    queries = [thumbnails(path) for path in query_paths]
    database = {int(i): thumbnails(database_paths[i]) for i in np.unique(indices[indices != EMPTY])}
    cell = tuple(max(image.shape[axis] for image in [*queries, *database.values()]) for axis in (0, 1))
    rows = []
    for query, row, marks in zip(queries, indices, relevant if relevant is not None else [None] * len(queries)):
        frames = [BACKGROUND if i == EMPTY else _mark_colour(marks, slot) for slot, i in enumerate(row)]
        tiles = [_tile(database.get(int(i)), cell, colour) for i, colour in zip(row, frames)]
        rows.append(_join([_tile(query, cell, QUERY), _join(tiles, axis=1, gap=SPACING)], axis=1, gap=QUERY_GAP))
    return _join(rows, axis=0, gap=SPACING)


def _mark_colour(marks: np.ndarray | None, slot: int) -> tuple[int, int, int]:
    return UNKNOWN if marks is None else RELEVANT if marks[slot] else NOT_RELEVANT


def _tile(thumbnail: np.ndarray | None, cell: tuple[int, int], frame: int | tuple[int, int, int]) -> np.ndarray:
    """``thumbnail`` centred in a ``cell`` of background, framed ``BORDER`` pixels wide."""
    height, width = cell
    tile = np.empty((height + 2 * BORDER, width + 2 * BORDER, 3), dtype=np.uint8)
    tile[:] = frame
    tile[BORDER:-BORDER, BORDER:-BORDER] = BACKGROUND
    if thumbnail is not None:
        top, left = BORDER + (height - thumbnail.shape[0]) // 2, BORDER + (width - thumbnail.shape[1]) // 2
        tile[top : top + thumbnail.shape[0], left : left + thumbnail.shape[1]] = thumbnail
    return tile


def _join(images: Sequence[np.ndarray], axis: int, gap: int) -> np.ndarray:
    """``images`` side by side (``axis=1``) or stacked (``axis=0``), ``gap`` background pixels apart."""
    if not images:
        return np.full((0, 0, 3), BACKGROUND, dtype=np.uint8)
    shape = list(images[0].shape)
    shape[axis] = gap
    spacer = np.full(shape, BACKGROUND, dtype=np.uint8)
    parts = [part for image in images for part in (spacer, image)][1:]
    return np.concatenate(parts, axis=axis)


# --- run folders ------------------------------------------------------------------------------


def write_gallery_inputs(scene: Scene, relevance: Mapping[str, sparse.csr_matrix], output_dir: Path) -> None:
    """Write ``images.csv`` and ``relevance/<ground truth>.npz`` into a run folder (module docstring)."""
    sets = (("database", scene.database), ("query", scene.queries))
    frames = [
        pd.DataFrame({"set": label, "index": range(len(images)), "name": images.names,
                      "path": [os.path.abspath(path) for path in images.paths]})
        for label, images in sets
    ]  # fmt: skip
    pd.concat(frames, ignore_index=True).to_csv(output_dir / IMAGES_FILE, index=False)
    for name, matrix in relevance.items():
        matrix = sparse.csr_matrix(matrix, dtype=bool)
        arrays = {"indptr": matrix.indptr, "indices": matrix.indices, "shape": np.asarray(matrix.shape)}
        save_arrays(relevance_file(output_dir, name), arrays)


def relevance_file(run: Path, groundtruth: str) -> Path:
    """Where a run keeps the relevance of ``groundtruth`` (its `safe_name`)."""
    return run / RELEVANCE_FOLDER / f"{safe_name(groundtruth)}.npz"


def load_relevance(path: Path, shape: tuple[int, int] | None = None) -> sparse.csr_matrix:
    """A relevance matrix written by `write_gallery_inputs` (of ``shape``, queries x database images,
    when given); a `DataFileError` naming the file when it is not one."""
    arrays = load_arrays(path, RERUN)
    try:
        data = np.ones(len(arrays["indices"]), dtype=bool)
        matrix = sparse.csr_matrix((data, arrays["indices"], arrays["indptr"]), shape=tuple(arrays["shape"]))
        matrix.check_format(full_check=True)
    except (KeyError, ValueError, TypeError, IndexError) as error:
        raise DataFileError(path, f"not a relevance matrix ({error})", RERUN) from None
    if shape is not None and matrix.shape != shape:
        raise DataFileError(path, f"a relevance matrix of shape {matrix.shape}, not {shape} as images.csv", RERUN)
    return matrix


@dataclass
class GalleryInputs:
    """What the galleries of one run read: image files per set, the chosen ground truth's
    relevance (``None`` without one) and the descriptor rankings' ``indices`` by name;
    ``outside``: listed images that may not be read (`read`), whose galleries are not drawn."""

    query_names: list[str]
    query_paths: list[str]
    database_paths: list[str]
    relevance: sparse.csr_matrix | None
    rankings: dict[str, np.ndarray]
    outside: list[str]

    @classmethod
    def read(
        cls, run: Path, groundtruth: str | None, image_roots: Sequence[str | os.PathLike] | None = ()
    ) -> "GalleryInputs | None":
        """The inputs in ``run``, ``None`` when it has no ``images.csv`` (a run of an earlier version).
        Every file read lies inside ``run`` (`run_file`); so must its images, or inside one of
        ``image_roots`` (``None``: anywhere, for the run's own report, whose images its config named)."""
        images_file = run_file(run, IMAGES_FILE)
        if not images_file.is_file():
            return None
        images = pd.read_csv(images_file, dtype={"set": str, "name": str, "path": str}, keep_default_na=False)
        missing = [c for c in ("set", "index", "name", "path") if c not in images.columns]
        if missing:
            raise ValueError(f"{images_file}: missing columns {missing} (found {list(images.columns)})")
        queries, database = (images[images["set"] == s].sort_values("index") for s in ("query", "database"))
        relevance_path = run_file(run, relevance_file(run, groundtruth).relative_to(run)) if groundtruth else None
        shape = (len(queries), len(database))
        found = relevance_path is not None and relevance_path.is_file()
        relevance = load_relevance(relevance_path, shape) if found else None
        rankings = {}
        for path in sorted(run_file(run, RANKINGS_FOLDER).glob("*.npz")):
            arrays = load_arrays(run_file(run, path.relative_to(run)), RERUN)
            if str(arrays.get("kind", "")) == "descriptor":
                indices = ranking_indices(arrays, path, len(queries), len(database))
                rankings[str(arrays.get("name", path.stem))] = indices  # the file name is its safe_name
        outside = [] if image_roots is None else outside_roots(images["path"], [run, *image_roots])
        return cls(list(queries["name"]), list(queries["path"]), list(database["path"]), relevance, rankings, outside)


def ranking_indices(arrays: Mapping[str, np.ndarray], path: Path, queries: int, database: int) -> np.ndarray:
    """A ranking file's ``indices``: integers ``[queries, K]`` into the database (`EMPTY` for none); a
    `DataFileError` naming the file otherwise."""
    indices = arrays.get("indices")
    if (
        indices is None
        or indices.dtype.kind not in "iu"
        or indices.ndim != 2
        or len(indices) != queries
        or (indices.size and (indices.min() < EMPTY or indices.max() >= database))
    ):
        shape = None if indices is None else f"{indices.dtype} {indices.shape}"
        raise DataFileError(
            path,
            f"indices {shape} are not a ranking of {queries} queries into {database} database images "
            f"(integers [{queries}, K], {EMPTY} for none; {IMAGES_FILE} lists the images)",
            RERUN,
        )
    return indices


# --- which queries, and their outcome ------------------------------------------------------------


def representative_k(ks: Sequence[int], k: int) -> int:
    """The k of a paradigm whose outcome a gallery of the top ``k`` shows: the largest at most
    ``k`` (the estimate used only images shown), else the smallest."""
    within = [value for value in ks if value <= k]
    return max(within) if within else min(ks)


def at_representative_k(errors: pd.DataFrame, k: int) -> pd.DataFrame:
    """The rows of a per-query error table (`QUERY_ERROR_COLUMNS`, one ranking) at each
    paradigm's `representative_k`."""
    if errors.empty:
        return errors
    chosen = {paradigm: representative_k(sorted(set(rows["k"])), k) for paradigm, rows in errors.groupby("paradigm")}
    return errors[errors["k"] == errors["paradigm"].map(chosen)]


def query_scores(errors: pd.DataFrame, scale: tuple[float, float]) -> pd.Series:
    """Per query (the index), the mean capped pose error at ``scale`` (the loosest threshold,
    ``(metres, degrees)``) over the rows of ``errors`` (`at_representative_k`); rows of a query
    estimated without a reference pose do not count."""
    unposed = (errors["failure"].fillna("") == "") & errors["position_error_m"].isna()
    rows = errors[~unposed]
    return capped_pose_error(rows, scale).groupby(rows["query"]).mean()


def select_queries(names: Sequence[str], scores: pd.Series, settings: GallerySettings) -> list[tuple[int, str]]:
    """``(query index, why shown)`` of the queries of one ranking's gallery (module docstring):
    the worst first (``worst 1`` is the largest score), then the random ones in the scene's order."""
    if settings.queries == "all":
        return [(index, "") for index in range(len(names))]
    ordered = scores.rename("score").rename_axis("query").reset_index()
    ordered = ordered.sort_values(["score", "query"], ascending=[False, True]).head(settings.worst)
    position = {name: index for index, name in enumerate(names)}
    worst = np.array([position[name] for name in ordered["query"]], dtype=np.int64)
    rest = np.setdiff1d(np.arange(len(names)), worst)
    drawn = np.random.default_rng(settings.seed).choice(rest, size=min(settings.random, len(rest)), replace=False)
    return [(int(q), f"worst {n + 1}") for n, q in enumerate(worst)] + [(int(q), "random") for q in sorted(drawn)]


def outcome_texts(errors: pd.DataFrame) -> pd.Series:
    """Per query (the index), each paradigm and method's outcome as Markdown (`md_text`), ``<br>``-separated:
    ``approximation ewb k=5: 0.42 m, 1.3°``, ``...: failed (reason)`` or ``...: no reference pose``
    (positions in the errors' ``position_unit``, metres for a run of an earlier version)."""
    if errors.empty:
        return pd.Series(dtype=str)
    label = errors["paradigm"] + " " + errors["method"] + " k=" + errors["k"].astype(int).astype(str) + ": "
    failure = errors["failure"].fillna("")
    unit = errors["position_unit"] if "position_unit" in errors else METRES
    errors_text = (
        errors["position_error_m"].map("{:.2f} ".format)
        + unit
        + ", "
        + errors["rotation_error_deg"].map("{:.1f}°".format)
    )
    outcome = np.where(
        failure != "",
        "failed (" + failure + ")",
        np.where(errors["position_error_m"].isna(), "no reference pose", errors_text),
    )
    text = (label + outcome).map(md_text)
    return text.groupby(errors["query"]).agg("<br>".join)


# --- the report section --------------------------------------------------------------------------


def gallery_section(
    writer: ReportWriter,
    run_dirs: Sequence[Path],
    groundtruth: str | None,
    settings: GallerySettings,
    scale: tuple[float, float],
    thumbnail_cache: str | os.PathLike | None,
    image_roots: Sequence[str | os.PathLike] | None = (),
    unit: str = METRES,
) -> None:
    """The report's ``Galleries`` section: one table per run and descriptor ranking, its rows
    drawn into ``galleries/``; ``scale``: the loosest threshold ``(position in unit, degrees)``;
    ``thumbnail_cache``: see `Thumbnails`; ``image_roots``: folders besides each run whose images
    may be read (`GalleryInputs.read`)."""
    started = time.perf_counter()
    writer.heading("Galleries")
    relevance = f"relevant under {md_text(groundtruth)}" if groundtruth else "no ground truth: relevance unknown (grey)"
    writer.text(
        f"Per query: the query (blue frame), then its top {settings.k} database images, rank 1 first, framed green "
        f"when relevant and red when not ({relevance}); the outcome is each paradigm's at the largest k <= "
        f"{settings.k} (else its smallest). "
        + (
            "Every query."
            if settings.queries == "all"
            else f"The {settings.worst} worst queries (largest mean capped error at the loosest threshold, "
            f"{md_text(threshold_label(*scale, unit))}, failures counting 1), "
            f"then {settings.random} drawn at random (seed {settings.seed})."
        )
        + " `relevant`: relevant images among those shown."
    )
    folder = writer.directory / GALLERY_FOLDER
    shutil.rmtree(folder, ignore_errors=True)
    thumbnails = Thumbnails(settings.thumbnail_size, thumbnail_cache)
    rows = 0
    for number, run in enumerate(run_dirs):
        prefix = f"run{number}_" if len(run_dirs) > 1 else ""
        rows += run_galleries(writer, run, prefix, groundtruth, settings, scale, thumbnails, image_roots)
    log.info("galleries: %d queries in %.1f s", rows, time.perf_counter() - started)


def run_galleries(
    writer: ReportWriter,
    run: Path,
    prefix: str,
    groundtruth: str | None,
    settings: GallerySettings,
    scale: tuple[float, float],
    thumbnails: Thumbnails,
    image_roots: Sequence[str | os.PathLike] | None = (),
) -> int:
    """The galleries of one run's descriptor rankings; returns how many rows were drawn."""
    inputs = GalleryInputs.read(run, groundtruth, image_roots)
    if inputs is None or not inputs.rankings:
        reason = f"no {IMAGES_FILE}, written by evaluate.py since 0.6" if inputs is None else "no descriptor ranking"
        writer.text(f"No galleries for {md_code(run)} ({reason}).")
        return 0
    if inputs.outside:
        log.warning(
            "galleries of %s not drawn: %d images of its %s lie outside the run folder and the folders "
            "given by --images, e.g. %s",
            run,
            len(inputs.outside),
            IMAGES_FILE,
            inputs.outside[0],
        )
        writer.text(
            f"No galleries for {md_code(run)}: {len(inputs.outside)} images its {md_code(IMAGES_FILE)} lists lie "
            "outside the run folder; give the dataset's folder to report.py (`--images DIR`) to draw them."
        )
        return 0
    if groundtruth is not None and inputs.relevance is None:
        missing = relevance_file(run, groundtruth).relative_to(run)
        writer.text(f"{md_code(run)} has no {md_code(missing)}: frames are grey (relevance unknown).")
    errors = read_table(run_file(run, TABLES["query_errors"].file), TABLES["query_errors"])
    rows = 0
    for name, indices in inputs.rankings.items():
        title = md_text(name) + (f" ({md_code(run)})" if prefix else "")
        try:
            rows += ranking_gallery(
                writer,
                title,
                Path(GALLERY_FOLDER) / f"{prefix}{safe_name(name)}",
                indices,
                inputs,
                errors[errors["ranking"] == name],
                settings,
                scale,
                thumbnails,
            )
        except FileNotFoundError as error:  # the dataset moved since the run: the report is still written
            log.warning("gallery of %s in %s not drawn: %s", name, run, error)
            writer.text(
                f"Gallery of {md_text(name)} not drawn: {md_text(error)} (listed in {md_code(run / IMAGES_FILE)})."
            )
    return rows


def ranking_gallery(
    writer: ReportWriter,
    title: str,
    folder: Path,
    indices: np.ndarray,
    inputs: GalleryInputs,
    errors: pd.DataFrame,
    settings: GallerySettings,
    scale: tuple[float, float],
    thumbnails: Thumbnails,
) -> int:
    """One ranking's gallery table; its row images are ``<folder>/<row>.jpg`` below the report."""
    at_k = at_representative_k(errors, settings.k)
    chosen = select_queries(inputs.query_names, query_scores(at_k, scale), settings)
    queries = np.array([q for q, _ in chosen], dtype=np.int64)
    top = indices[queries, : settings.k]
    relevant = relevant_hits(top, inputs.relevance[queries]) if inputs.relevance is not None else None
    outcomes = outcome_texts(at_k)
    (writer.directory / folder).mkdir(parents=True, exist_ok=True)
    lines = [f"| query | shown | query, top {settings.k} | relevant | outcome |", "| --- | --- | --- | --- | --- |"]
    for row, (q, why) in enumerate(chosen):
        marks = relevant[row : row + 1] if relevant is not None else None
        image = gallery_image([inputs.query_paths[q]], inputs.database_paths, top[row : row + 1], marks, thumbnails)
        file = folder / f"{row:04d}.jpg"
        Image.fromarray(image).save(writer.directory / file, quality=JPEG_QUALITY)
        name = inputs.query_names[q]
        hits = f"{int(marks.sum())}/{int((top[row] != EMPTY).sum())}" if marks is not None else "–"
        lines.append(
            f"| {md_text(name)} | {why} | ![{md_text(name)}]({file.as_posix()}) | {hits} | {outcomes.get(name, '–')} |"
        )
    writer.heading(f"Gallery: {title}", 3)
    writer.text("\n".join(lines) if chosen else "No query to show.")
    return len(chosen)
