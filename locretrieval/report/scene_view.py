"""`write_scene_view`: the scene in 3D, one self-contained interactive HTML file (``scene_3d.html``).

It shows the database cameras as frusta, each query's reference pose (frustum and centre), the
global map's points when the run built one, and the estimated query poses of one ranking x
paradigm x method x k at a time, chosen in a dropdown: a marker at each estimated centre, its
optical axis and a line to its reference centre (the position error). plotly.js is embedded,
so the file opens from disk with no server and no network.

Conventions: poses are world-to-camera ``(q, t)`` with ``q = (w, x, y, z)`` (kapture, COLMAP),
``x_cam = R(q) x_world + t``; camera centres ``c = -R^T t``; the camera looks along its +z axis;
coordinates are in the scene's unit (metres), angles in degrees.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from locretrieval import geometry
from locretrieval.config import require
from locretrieval.folders import inside
from locretrieval.report.html import with_script_policy
from locretrieval.report.markdown import md_link
from locretrieval.scene import ImageSet, Scene
from locretrieval.scene.types import METRES

if TYPE_CHECKING:
    import plotly.graph_objects as go

log = logging.getLogger(__name__)

#: The file `write_scene_view` writes into a run folder, linked from the report.
SCENE_VIEW_FILE = "scene_3d.html"
#: Columns of an estimated-pose table (`locretrieval.estimates.estimated_pose_table`).
SELECTION = ["ranking", "paradigm", "method", "k"]
POSE_COLUMNS = ["qw", "qx", "qy", "qz", "tx", "ty", "tz"]
#: `frustum_depth`: the neighbour whose median distance sets the frusta's size.
NEIGHBOURS = 8
#: Each camera's wireframe as one stroke through its centre ``c`` and far corners ``f1..f4``
#: (f1 f2 f3 f4 f1 c f2 f3 c f4 covers the 8 edges), then a gap.
FRUSTUM_STROKE = [1, 2, 3, 4, 1, 0, 2, 3, 0, 4]
COLORS = {"database": "#7f7f7f", "map": "#6baed6", "reference": "#2ca02c", "estimate": "#d62728"}


@dataclass
class SceneViewSettings:
    """The ``report.scene_view`` config section.

    ``enabled``: write ``scene_3d.html``; ``max_cameras`` / ``max_queries``: database cameras and
    queries drawn at most (evenly spaced in the scene's order); ``max_map_points``: global-map
    points drawn at most (a seeded sample); ``frustum_depth_m``: depth of the drawn frusta in
    metres (``None``: the median distance between neighbouring database cameras).
    """

    enabled: bool
    max_cameras: int
    max_queries: int
    max_map_points: int
    frustum_depth_m: float | None

    def __post_init__(self) -> None:
        for key in ("max_cameras", "max_queries", "max_map_points"):
            require(getattr(self, key) >= 0, key, f"must be >= 0, got {getattr(self, key)}")
        require(
            self.frustum_depth_m is None or self.frustum_depth_m > 0,
            "frustum_depth_m",
            f"must be a positive distance or null, got {self.frustum_depth_m}",
        )


def write_scene_view(
    path: str | Path,
    scene: Scene,
    estimated_poses: pd.DataFrame,
    map_points: np.ndarray | None,
    settings: SceneViewSettings,
) -> Path:
    """Write ``scene_figure`` as a self-contained HTML file (plotly.js embedded, a Content-Security-Policy
    allowing its own scripts only: `with_script_policy`); returns its path."""
    path = Path(path)
    figure = scene_figure(scene, estimated_poses, map_points, settings)
    path.parent.mkdir(parents=True, exist_ok=True)
    page = figure.to_html(include_plotlyjs=True, full_html=True, config={"displaylogo": False, "responsive": True})
    path.write_text(with_script_policy(page), encoding="utf-8")  # its own scripts only: names are data
    log.info("3D view written to %s (%.1f MB)", path, path.stat().st_size / 2**20)
    return path


def scene_figure(
    scene: Scene, estimated_poses: pd.DataFrame, map_points: np.ndarray | None, settings: SceneViewSettings
) -> "go.Figure":
    """The figure: fixed traces (database frusta, map points, reference poses), then two traces
    per ranking x paradigm x method x k (estimated centres, named ``"<ranking> / <paradigm>
    <method> / k=<k>"`` with that selection in ``meta``; their axes and error lines), shown one
    selection at a time by the dropdown. ``estimated_poses``: rows of query name, `SELECTION`
    and `POSE_COLUMNS` (world-to-camera, wxyz); queries beyond ``settings.max_queries`` are left out."""
    import plotly.graph_objects as go

    depth = settings.frustum_depth_m or frustum_depth(scene.database.centers)
    cameras = evenly_spaced(len(scene.database), settings.max_cameras)
    queries = evenly_spaced(len(scene.queries), settings.max_queries)
    fixed = [frusta_trace(scene.database.subset(cameras), depth, "database cameras", COLORS["database"])]
    if map_points is not None and len(map_points):
        fixed.append(map_trace(map_points, settings.max_map_points, surroundings(scene, depth)))
    fixed += reference_traces(scene.queries, queries, depth)
    selections = estimate_traces(scene.queries, queries, estimated_poses, depth, scene.position_unit)
    for trace in selections[0] if selections else ():
        trace.visible = True
    figure = go.Figure(fixed + [trace for pair in selections for trace in pair])
    unit = scene.position_unit
    figure.update_layout(
        title=f"{scene.name}: {len(cameras)} of {len(scene.database)} database cameras, {len(queries)} of "
        f"{len(scene.queries)} queries (frusta {depth:.2g} {unit} deep)",
        scene={"aspectmode": "data", **{f"{axis}axis_title": f"{axis} ({unit})" for axis in "xyz"}},
        legend={"itemsizing": "constant"},
        margin={"l": 0, "r": 0, "t": 40, "b": 0},
        updatemenus=[selection_menu(len(fixed), selections)] if selections else [],
    )
    return figure


def frustum_depth(centers: np.ndarray) -> float:
    """Metres: half the median distance from a database camera to its 8th nearest (cameras a few
    centimetres apart, e.g. one spot's headings, do not make it vanish); 2% of the extent if zero."""
    from scipy.spatial import cKDTree

    if len(centers) < 2:
        return 1.0
    distances, _ = cKDTree(centers).query(centers, k=min(NEIGHBOURS, len(centers) - 1) + 1)
    spacing = 0.5 * float(np.median(distances[:, -1]))
    return spacing if spacing > 0 else 0.02 * float(np.linalg.norm(np.ptp(centers, axis=0))) or 1.0


def surroundings(scene: Scene, depth: float) -> tuple[np.ndarray, np.ndarray]:
    """The box ``(low, high)`` around every camera centre (database, queries with a pose), enlarged
    by half its diagonal (at least 4 frustum depths): map points outside it are left out."""
    centers = np.concatenate([scene.database.centers, scene.queries.centers[scene.queries.has_pose]])
    low, high = centers.min(axis=0), centers.max(axis=0)
    margin = max(0.5 * float(np.linalg.norm(high - low)), 4 * depth)
    return low - margin, high + margin


def xyz(points: np.ndarray) -> dict[str, np.ndarray]:
    """A trace's ``x``, ``y``, ``z`` from ``points [N, 3]``, in float32 (plotly writes them as
    binary arrays: half the size of float64; a millimetre is kept within 8 km of the origin)."""
    points = np.asarray(points, dtype=np.float32)
    return {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]}


def evenly_spaced(count: int, limit: int) -> np.ndarray:
    """At most ``limit`` indices of ``range(count)``, evenly spaced, first included."""
    if count <= limit:
        return np.arange(count)
    return np.unique(np.linspace(0, count - 1, limit).round().astype(int))


def frusta_lines(qvec: np.ndarray, tvec: np.ndarray, intrinsics: np.ndarray, depth: float) -> np.ndarray:
    """``[N * 11, 3]`` line vertices of N camera wireframes (world-to-camera wxyz poses, intrinsics
    rows ``(fx, fy, cx, cy, width, height)``): centre to the image corners at ``depth`` metres along
    the optical axis, NaN rows between cameras."""
    corners = geometry.frustum_corners(qvec, tvec, intrinsics, 0.0, depth)[:, 4:]  # far corners
    points = np.concatenate([geometry.camera_centers(qvec, tvec)[:, None], corners], axis=1)
    strokes = points[:, FRUSTUM_STROKE]
    gaps = np.full((len(points), 1, 3), np.nan)
    return np.concatenate([strokes, gaps], axis=1).reshape(-1, 3)


def frusta_trace(
    images: ImageSet, depth: float, name: str, color: str, legendgroup: str | None = None
) -> "go.Scatter3d":
    """The wireframes of ``images`` (every one with a pose) as one line trace."""
    import plotly.graph_objects as go

    posed = images.has_pose
    lines = frusta_lines(images.qvec[posed], images.tvec[posed], images.intrinsics[posed], depth)
    return go.Scatter3d(
        **xyz(lines),
        mode="lines",
        name=f"{name} ({int(posed.sum())})",
        line={"color": color, "width": 1},
        hoverinfo="skip",
        legendgroup=legendgroup or name,
    )


def map_trace(points: np.ndarray, limit: int, box: tuple[np.ndarray, np.ndarray]) -> "go.Scatter3d":
    """At most ``limit`` of the global map's ``points [P, 3]`` (world, metres) inside ``box``
    (`surroundings`: stray triangulations far away would shrink the cameras to a dot), a seeded sample."""
    import plotly.graph_objects as go

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    inside = points[((points >= box[0]) & (points <= box[1])).all(axis=1)]
    shown = (
        inside
        if len(inside) <= limit
        else inside[np.sort(np.random.default_rng(0).choice(len(inside), limit, replace=False))]
    )
    far = f", {len(points) - len(inside)} far away left out" if len(inside) < len(points) else ""
    return go.Scatter3d(
        **xyz(shown),
        mode="markers",
        name=f"map points ({len(shown)} of {len(points)}{far})",
        marker={"size": 1.5, "color": COLORS["map"], "opacity": 0.6},
        hoverinfo="skip",
    )


def reference_traces(queries: ImageSet, drawn: np.ndarray, depth: float) -> list["go.Scatter3d"]:
    """The reference poses of the ``drawn`` queries that have one: frusta, and centres named on hover."""
    import plotly.graph_objects as go

    chosen = drawn[queries.has_pose[drawn]]
    if not len(chosen):
        return []
    centers = queries.centers[chosen]
    names = [f"#{i}: {queries.names[i]}" for i in chosen]
    return [
        frusta_trace(queries.subset(chosen), depth, "query reference poses", COLORS["reference"], "reference"),
        go.Scatter3d(
            **xyz(centers),
            mode="markers",
            name="reference centres",
            marker={"size": 2.5, "color": COLORS["reference"]},
            hovertext=names,
            hoverinfo="text",
            legendgroup="reference",
            showlegend=False,
        ),
    ]


def estimate_traces(
    queries: ImageSet, drawn: np.ndarray, estimated_poses: pd.DataFrame, depth: float, unit: str = METRES
) -> list[tuple["go.Scatter3d", "go.Scatter3d"]]:
    """Per ranking x paradigm x method x k: its estimated centres and its lines; descriptor
    rankings first (``ranking_kind``, when given), then by name, paradigm, method and k; errors in ``unit``."""
    missing = [c for c in ["query", *SELECTION, *POSE_COLUMNS] if c not in estimated_poses]
    if missing:
        raise ValueError(f"estimated poses lack columns {missing} (found {list(estimated_poses.columns)})")
    index = {name: i for i, name in enumerate(queries.names)}
    rows = estimated_poses.assign(_query=estimated_poses["query"].map(index))
    unknown = rows["_query"].isna()
    if unknown.any():
        raise ValueError(f"estimated poses of queries not in the scene, e.g. {rows.loc[unknown, 'query'].iloc[0]!r}")
    rows = rows[rows["_query"].isin(set(drawn.tolist()))]
    groups = sorted(rows.groupby(SELECTION, sort=True), key=lambda item: _is_baseline(item[1]))  # stable
    return [selection_traces(queries, group, dict(zip(SELECTION, key)), depth, unit) for key, group in groups]


def _is_baseline(rows: pd.DataFrame) -> bool:
    """Rows of a ground-truth or baseline ranking (listed after the descriptors)."""
    return "ranking_kind" in rows and rows["ranking_kind"].iloc[0] != "descriptor"


def selection_traces(
    queries: ImageSet, rows: pd.DataFrame, selection: dict, depth: float, unit: str = METRES
) -> tuple["go.Scatter3d", "go.Scatter3d"]:
    """One selection's estimated centres (hover: query index, position and rotation errors) and,
    per query, its optical axis (``depth`` long) and the segment to its reference centre."""
    import plotly.graph_objects as go

    qvec, tvec = rows[POSE_COLUMNS[:4]].to_numpy(float), rows[POSE_COLUMNS[4:]].to_numpy(float)
    members = rows["_query"].to_numpy(int)
    centers = geometry.camera_centers(qvec, tvec)
    axes = geometry.quaternion_to_matrix(qvec)[:, 2, :]  # +z of the camera in world coordinates
    reference = queries.centers[members]
    position = geometry.position_errors(centers, reference)
    rotation = geometry.rotation_errors_deg(qvec, queries.qvec[members])
    segments = np.stack(
        [
            centers,
            centers + depth * axes,
            np.full_like(centers, np.nan),
            reference,
            centers,
            np.full_like(centers, np.nan),
        ],
        axis=1,
    ).reshape(-1, 3)
    label = f"{selection['ranking']} / {selection['paradigm']} {selection['method']} / k={selection['k']}"
    meta = {**selection, "k": int(selection["k"])}
    markers = go.Scatter3d(
        **xyz(centers),
        mode="markers",
        name=f"{label} ({len(rows)} estimated)",
        marker={"size": 3, "color": COLORS["estimate"]},
        legendgroup=label,
        meta=meta,
        visible=False,
        customdata=np.stack([members, position, rotation], axis=1).astype(np.float32),
        hovertemplate="query #%{customdata[0]}<br>%{customdata[1]:.2f} "
        + unit
        + ", %{customdata[2]:.1f}°<extra>estimate</extra>",
    )
    lines = go.Scatter3d(
        **xyz(segments),
        mode="lines",
        name=f"{label}: axes, errors",
        line={"color": COLORS["estimate"], "width": 2},
        legendgroup=label,
        showlegend=False,
        hoverinfo="skip",
        visible=False,
        meta=meta,
    )
    return markers, lines


def selection_menu(num_fixed: int, selections: Sequence[tuple]) -> dict:
    """The dropdown: one entry per selection, showing the fixed traces and that selection's two
    (the first is active, as `scene_figure` shows it at first); a last entry hides every estimate."""
    num_traces = num_fixed + 2 * len(selections)
    buttons = []
    for n, (markers, _) in enumerate(selections):
        visible = [True] * num_fixed + [False] * (num_traces - num_fixed)
        visible[num_fixed + 2 * n] = visible[num_fixed + 2 * n + 1] = True
        buttons.append({"label": markers.legendgroup, "method": "restyle", "args": [{"visible": visible}]})
    buttons.append(
        {
            "label": "no estimate",
            "method": "restyle",
            "args": [{"visible": [True] * num_fixed + [False] * (num_traces - num_fixed)}],
        }
    )
    return {
        "buttons": buttons,
        "active": 0,
        "direction": "down",
        "x": 0.0,
        "xanchor": "left",
        "y": 1.0,
        "yanchor": "top",
    }


def link(run_dirs: Sequence[Path], output_dir: Path) -> str | None:
    """A Markdown line linking every run's ``scene_3d.html`` (relative to ``output_dir``; one that resolves
    outside its run is not linked), or ``None``."""
    found = [
        Path(run) / SCENE_VIEW_FILE
        for run in run_dirs
        if (Path(run) / SCENE_VIEW_FILE).is_file() and inside(Path(run) / SCENE_VIEW_FILE, run)
    ]
    if not found:
        return None
    targets = [Path(os.path.relpath(path, output_dir)).as_posix() for path in found]
    return "3D view: " + ", ".join(md_link(target, target) for target in targets)
