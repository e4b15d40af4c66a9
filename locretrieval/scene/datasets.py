"""Benchmark datasets as Hydra-instantiable loaders (``configs/data/*.yaml``).

Every data config names kapture folders relative to a data root (``LOCRETRIEVAL_DATA`` or
``paths.data_dir``), the query tags, how LTVL files name images and the frustum far plane
of the ground truth. Folder entries may be glob patterns (RobotCar Seasons v2 has one
mapping folder per location: ``RobotCar_Seasons-v2/*/mapping``).
"""

from __future__ import annotations

import glob
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from filelock import FileLock

from locretrieval.cache import config_key
from locretrieval.config import build_part, validated
from locretrieval.scene.kapture_io import load_kapture_scene
from locretrieval.scene.ltvl import LtvlNames
from locretrieval.scene.types import Scene

log = logging.getLogger(__name__)


class DatasetNotFoundError(FileNotFoundError):
    """A dataset folder is missing; the message says where it was expected and how to get it."""


def _as_list(folders: str | Path | Sequence[str | Path]) -> list[str]:
    return [str(folders)] if isinstance(folders, (str, Path)) else [str(folder) for folder in folders]


def resolve_folders(root: Path, entries: Sequence[str], what: str, missing_message: str | None) -> list[list[Path]]:
    """The folders of each entry (a path or glob pattern relative to ``root``; absolute paths stay
    as they are), sorted; raises `DatasetNotFoundError` for an entry matching none: its path, then
    ``missing_message`` (where a published dataset is expected and how to get it), or for a user's
    own data (``None``) ``what`` the entry is (``dataset 'kapture', its mapping``) and, for a
    relative entry, the data root it is under."""
    resolved = []
    for entry in entries:
        target = root / Path(entry).expanduser()
        if glob.has_magic(entry):
            matches = sorted(Path(path) for path in glob.glob(str(target)) if Path(path).is_dir())
        else:
            matches = [target] if target.is_dir() else []
        if not matches:
            if missing_message is not None:
                raise DatasetNotFoundError(f"kapture folder not found: {target}\n{missing_message}")
            under = "" if Path(entry).expanduser().is_absolute() else f" {entry!r} under the data root {root}"
            raise DatasetNotFoundError(f"kapture folder not found: {target} ({what}{under})")
        resolved.append(matches)
    return resolved


def _missing_message(name: str, root: Path, mapping: list[str], queries: list[str], install: str) -> str:
    return "\n".join(
        [
            f"Dataset {name!r} expects, under the data root {root} ($LOCRETRIEVAL_DATA if set, else paths.data_dir, "
            f"e.g. `python evaluate.py paths.data_dir=/datasets`): mapping {', '.join(mapping)}; "
            f"queries {', '.join(queries)}",
            f"To obtain the dataset (run from {root}):",
            *(f"  {line}" for line in install.strip().splitlines()),
        ]
    )


def load_dataset(
    name: str,
    root: str | Path,
    mapping: str | Sequence[str],
    queries: str | Sequence[str],
    *,
    ltvl_names: Any,
    frustum_far: float | None,
    query_tags: Sequence[str] | None,
    name_tags: Mapping[str, str] | None,
    install: str | None,
    unsupported: Mapping[str, str] | None,
) -> Scene:
    """A `Scene` from kapture folders under ``root``.

    ``mapping``/``queries``: folders (or glob patterns) relative to ``root``. ``query_tags``:
    one tag per query entry, given to every folder it matches (default: the folder name).
    ``name_tags``: ``{tag: regex}`` on image names (e.g. RobotCar's day/night conditions).
    ``ltvl_names`` (an `LtvlNames`, or its config node: ``data.ltvl_names``) and ``frustum_far``
    (metres) are dataset facts kept on the `Scene` (checked before any folder is read).
    ``install``: the commands that obtain a published dataset, shown when a folder is missing
    (``None`` or empty: a user's own data, whose missing folder is named with its key only).
    ``unsupported``: paradigm or ground-truth name -> why the dataset cannot run it (kept on the
    `Scene`; enabling one is an error at start-up).
    """
    ltvl_names = build_part(LtvlNames, ltvl_names, "data.ltvl_names", "data/ltvl_names")
    Scene.check_facts(name, ltvl_names, frustum_far)
    root = Path(root).expanduser()
    mapping_entries, query_entries = _as_list(mapping), _as_list(queries)
    if query_tags is not None and len(query_tags) != len(query_entries):
        raise ValueError(
            f"dataset {name!r}: {len(query_tags)} query_tags {list(query_tags)} "
            f"for {len(query_entries)} query entries {query_entries}"
        )
    message = _missing_message(name, root, mapping_entries, query_entries, install) if install else None
    mapping_matches = resolve_folders(root, mapping_entries, f"dataset {name!r}, its mapping", message)
    query_matches = resolve_folders(root, query_entries, f"dataset {name!r}, its queries", message)
    mapping_folders = [folder for matches in mapping_matches for folder in matches]
    query_folders = [folder for matches in query_matches for folder in matches]
    tags = None
    if query_tags is not None:
        tags = [str(tag) for tag, matches in zip(query_tags, query_matches) for _ in matches]
    scene = load_kapture_scene(
        name,
        mapping_folders,
        query_folders,
        query_tags=tags,
        name_tags=dict(name_tags) if name_tags else None,
        ltvl_names=ltvl_names,
        frustum_far=frustum_far,
    )
    scene.unsupported = dict(unsupported or {})
    return scene


def load_synthetic_dataset(
    name: str,
    cache_dir: str | Path,
    render: Any,
    ltvl_names: Any,
    frustum_far: float,
) -> Scene:
    """The built-in synthetic scene: rendered once per ``render`` settings into
    ``<cache_dir>/synthetic/<key>/{mapping,query}`` (kapture), then read like any dataset.

    ``render``: the ``data.render`` node (checked as `locretrieval.scene.synthetic.RenderSettings`);
    the folder key hashes its record (`RenderSettings.record`), so any change renders a new scene.
    """
    from locretrieval.device import resolve_device
    from locretrieval.scene.synthetic import RenderSettings  # the renderer only when the scene is not cached

    settings = validated(RenderSettings, render, "data.render")
    keyed = {k: v for k, v in settings.record().items() if k not in RENDER_ONLY_KEYS}
    keyed["device"] = resolve_device(settings.device).type  # "auto" keys what it resolves to: float results may differ
    folder = Path(cache_dir) / "synthetic" / config_key(keyed)
    folder.parent.mkdir(parents=True, exist_ok=True)
    # one process renders, the others (a multirun's jobs on one cache) wait and read its scene:
    # a second render would replace the folders the first process is reading
    with FileLock(folder.parent / f".{folder.name}.lock"):
        if not (folder / "synthetic_config.json").is_file():
            from locretrieval.scene.synthetic import render_synthetic_dataset

            log.info("rendering the synthetic scene into %s", folder)
            render_synthetic_dataset(settings, folder)
        else:
            log.info("synthetic scene cached in %s", folder)
    return load_dataset(
        name,
        folder,
        "mapping",
        ["query"],
        ltvl_names=ltvl_names,
        frustum_far=frustum_far,
        query_tags=["query"],
        name_tags=None,
        install=None,  # rendered above
        unsupported=None,
    )


#: Renderer keys that change how fast a scene renders, not what it contains.
RENDER_ONLY_KEYS = ("workers",)
