"""COLMAP models: a model and its image folder as a `Scene` (``data=colmap``), and the conversions
between our cameras and poses and pycolmap's.

Poses cross this boundary as world-to-camera ``(q wxyz, t)`` on our side and
``Rigid3d(Rotation3d(xyzw), t)`` (``cam_from_world``) on pycolmap's. Cameras keep COLMAP's
model, parameters and pixel convention, so they are copied as they are.

A scene read from a model holds its registered images (unregistered ones are reported and left
out), split into database and queries by ``data.split`` (`locretrieval.scene.split`), scaled to
metres (`locretrieval.scene.scale`), with the 3D points each image observes (the model's tracks:
the co-observation ground truth needs no SfM of ours) and the quality of the model as a pseudo
ground truth (`ReconstructionQuality`), logged here and written into the run's summary.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import sparse

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval import geometry
from locretrieval.config import ConfigError, build_part, unknown_key, validated
from locretrieval.errors import FIX_DATA_FILE, DataFileError
from locretrieval.scene.colmap_files import check_model_files, check_reconstruction
from locretrieval.scene.images import check_distinct_images, check_image_sizes, check_names, image_files
from locretrieval.scene.ltvl import LtvlNames
from locretrieval.scene.reconstruction import Observations, ReconstructionQuality
from locretrieval.scene.scale import KnownDistance, ScaleSettings, metric_alignment
from locretrieval.scene.split import SceneSplit
from locretrieval.scene.types import Camera, ImageSet, Scene

if TYPE_CHECKING:
    import pycolmap  # imported where it is used: a run without a COLMAP model does not load it

log = logging.getLogger(__name__)

#: The files of a COLMAP model folder, each ``<name>.bin`` or ``<name>.txt``.
MODEL_FILES = ("cameras", "images", "points3D")
#: The tag of the query images a split chooses.
QUERY_TAG = "query"


def to_pycolmap_camera(camera: Camera, camera_id: int | None = None) -> pycolmap.Camera:
    """The same camera as a ``pycolmap.Camera`` (model, size and parameters copied)."""
    import pycolmap

    converted = pycolmap.Camera(
        model=camera.model, width=camera.width, height=camera.height, params=list(camera.params)
    )
    if camera_id is not None:
        converted.camera_id = camera_id
    return converted


def to_rigid3d(qvec: np.ndarray, tvec: np.ndarray) -> pycolmap.Rigid3d:
    """``cam_from_world`` of a world-to-camera pose (q wxyz, t)."""
    import pycolmap

    w, x, y, z = np.asarray(qvec, dtype=np.float64)
    return pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([x, y, z, w])), np.asarray(tvec, dtype=np.float64))


def from_rigid3d(cam_from_world: pycolmap.Rigid3d) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera ``(q wxyz with w >= 0, t)`` of a pycolmap ``cam_from_world``."""
    x, y, z, w = cam_from_world.rotation.quat
    return geometry.normalize_quaternions(np.array([w, x, y, z])), np.asarray(
        cam_from_world.translation, dtype=np.float64
    )


def missing_model_files(folder: str | Path) -> list[str]:
    """What a COLMAP model ``folder`` lacks: the folder itself, or each of `MODEL_FILES`."""
    folder = Path(folder)
    if not folder.is_dir():
        return [f"COLMAP model folder {folder} not found"]
    return [
        f"{folder / name}.bin (or .txt) not found"
        for name in MODEL_FILES
        if not any((folder / f"{name}{suffix}").is_file() for suffix in (".bin", ".txt"))
    ]


def load_colmap_dataset(name: str, root: str | Path, model: str | Path, images: str | Path, **options: Any) -> Scene:
    """The `Scene` of the COLMAP ``model`` folder (``cameras``, ``images``, ``points3D``, binary or
    text) whose image names are relative to the ``images`` folder (both relative to ``root`` or
    absolute); the other keys of its ``data`` node are its `SceneOptions` (`SCENE_KEYS`)."""
    from locretrieval.scene.datasets import DatasetNotFoundError

    scene = SceneOptions.from_keys(name, options)
    model_folder, image_folder = Path(root).expanduser() / model, Path(root).expanduser() / images
    missing = missing_model_files(model_folder) + ([] if image_folder.is_dir() else [f"image folder {image_folder}"])
    if missing:
        raise DatasetNotFoundError(
            "COLMAP model or images not found:\n"
            + "\n".join(f"  {problem}" for problem in missing)
            + "\ndata.model is the folder of cameras, images and points3D (.bin or .txt, e.g. sparse/0), "
            "data.images the folder its image names are relative to; relative paths start at the data root "
            f"{root} ($LOCRETRIEVAL_DATA or paths.data_dir)."
        )
    reconstruction = read_model(model_folder)
    return reconstruction_scene(reconstruction, str(model_folder), image_folder, scene)


def read_model(folder: Path) -> pycolmap.Reconstruction:
    """The COLMAP model of ``folder``, its files checked before pycolmap reads them and what it read
    checked after (`locretrieval.scene.colmap_files`); a `DataFileError` naming the file otherwise."""
    import pycolmap

    check_model_files(folder)
    try:
        reconstruction = pycolmap.Reconstruction(folder)
    except Exception as error:  # pycolmap raises its own types (and ValueError, RuntimeError) for bad files
        raise DataFileError(folder, f"pycolmap cannot read this COLMAP model ({error})", FIX_DATA_FILE) from None
    check_reconstruction(reconstruction, folder)
    return reconstruction


#: The keys of a ``data`` node of a reconstruction (``data=colmap``, ``data=photos``) that are its
#: `SceneOptions`: the split, the scale (`ScaleSettings`' keys and ``known_distance``) and dataset facts.
SCENE_KEYS = (
    "split",
    "metres_per_unit",
    "known_distance",
    "unitless",
    "gps_max_error",
    "frustum_far",
    "ltvl_names",
    "unsupported",
)


@dataclass(frozen=True)
class SceneOptions:
    """What a scene read from a reconstruction is besides its files, checked before any file is
    read: its ``name``, the ``split`` choosing its queries (`SceneSplit`), its ``scale``
    (`ScaleSettings`, keys ``data.<key>``), and the dataset facts kept on the `Scene`, as for
    kapture data: ``ltvl_names``, ``frustum_far`` (metres) and ``unsupported`` (paradigm or
    ground truth -> why the dataset cannot run it)."""

    name: str
    split: SceneSplit
    scale: ScaleSettings
    ltvl_names: LtvlNames
    frustum_far: float | None
    unsupported: dict[str, str]

    @classmethod
    def from_keys(cls, name: str, keys: Mapping[str, Any]) -> SceneOptions:
        """The options of a ``data`` node's ``keys`` (each of `SCENE_KEYS`); a key missing or
        unknown is a `ConfigError` naming it."""
        unknown = [key for key in keys if key not in SCENE_KEYS]
        if unknown:
            raise ConfigError(unknown_key(f"data.{unknown[0]}", SCENE_KEYS))
        missing = [key for key in SCENE_KEYS if key not in keys]
        if missing:
            raise ConfigError(
                f"data.{missing[0]}: missing; a reconstruction's data node sets each of {list(SCENE_KEYS)}"
            )
        ltvl_names = build_part(LtvlNames, keys["ltvl_names"], "data.ltvl_names", "data/ltvl_names")
        Scene.check_facts(name, ltvl_names, keys["frustum_far"])
        scale_keys = ("metres_per_unit", "unitless", "gps_max_error")
        scale = validated(ScaleSettings, {"known_distance": None, **{key: keys[key] for key in scale_keys}}, "data")
        # known_distance: a section of its own (a nested optional one stays a mapping in `validated`)
        if keys["known_distance"] is not None:
            scale = dataclasses.replace(
                scale, known_distance=validated(KnownDistance, keys["known_distance"], "data.known_distance")
            )
        return cls(
            name,
            build_part(SceneSplit, keys["split"], "data.split", "data/split"),
            scale,
            ltvl_names,
            keys["frustum_far"],
            dict(keys["unsupported"] or {}),
        )


def reconstruction_scene(
    reconstruction: pycolmap.Reconstruction,
    model: str,
    image_folder: Path,
    scene: SceneOptions,
) -> Scene:
    """The `Scene` of a pycolmap ``reconstruction`` (transformed to metres in place) whose images
    are files of ``image_folder``, with the ``scene``'s options; ``model`` names it in errors and in
    the quality report."""
    folder_images = image_files(image_folder)
    by_name = {image.name: image for image in reconstruction.images.values()}
    registered = sorted(image.name for image in by_name.values() if image.has_pose)
    if not registered:
        raise DataFileError(model, "the model has no registered image")
    absent = sorted(set(registered) - set(folder_images))
    if absent:
        raise DataFileError(
            model,
            f"{len(absent)} of its {len(registered)} registered images are missing from the image folder "
            f"{image_folder}, e.g. {absent[:3]}; data.images must be the folder the model's image names are "
            "relative to",
        )
    found = sorted(set(folder_images) | set(by_name))
    unregistered = sorted(set(found) - set(registered))
    if unregistered:
        log.warning(
            "%s: %d of %d images are not registered in %s and are left out, e.g. %s",
            image_folder,
            len(unregistered),
            len(found),
            model,
            unregistered[:5],
        )
    check_names(Path(model), registered)
    check_distinct_images(image_folder, registered)
    alignment = metric_alignment(reconstruction, image_folder, registered, scene.scale, model)
    reconstruction.transform(alignment.new_from_old)
    images = registered_images(reconstruction, [by_name[name] for name in registered], image_folder, model)
    queries = scene.split.split(registered, folder_images)
    query_set = images.subset(queries)
    query_set.tags = [frozenset({QUERY_TAG}) for _ in query_set.names]
    residuals = alignment.gps_residuals
    quality = ReconstructionQuality(
        source=model,
        images=len(found),
        registered=len(registered),
        points=reconstruction.num_points3D(),
        mean_track_length=float(reconstruction.compute_mean_track_length()),
        mean_reprojection_error_px=float(reconstruction.compute_mean_reprojection_error()),
        scale_source=alignment.source,
        metres_per_unit=alignment.metres_per_unit,
        gps_images=alignment.gps_images,
        gps_residual_median_m=None if residuals is None else float(np.median(residuals)),
        gps_residual_rms_m=None if residuals is None else float(np.sqrt(np.mean(residuals**2))),
    )
    log.info("%s", quality.describe())
    return Scene(
        scene.name,
        images.subset(~queries),
        query_set,
        sources=[Path(model), image_folder],
        ltvl_names=scene.ltvl_names,
        frustum_far=scene.frustum_far,
        unsupported=scene.unsupported,
        observations=track_observations(reconstruction, registered),
        quality=quality,
    )


def registered_images(
    reconstruction: pycolmap.Reconstruction, images: Sequence[pycolmap.Image], folder: Path, model: str
) -> ImageSet:
    """The `ImageSet` of registered ``images`` (their cameras checked against the files' sizes; the
    model's values were checked where it was read, `read_model`)."""
    cameras = {  # checked by `read_model`
        camera_id: Camera(camera.model.name, int(camera.width), int(camera.height), tuple(map(float, camera.params)))
        for camera_id, camera in reconstruction.cameras.items()
    }
    names = [image.name for image in images]
    image_cameras = [cameras[image.camera_id] for image in images]
    check_image_sizes(folder, names, image_cameras, [f"{image.camera_id} in {model}" for image in images])
    poses = [from_rigid3d(image.cam_from_world()) for image in images]
    return ImageSet(
        names=names,
        image_root=folder,
        cameras=image_cameras,
        qvec=np.array([q for q, _ in poses]).reshape(-1, 4),
        tvec=np.array([t for _, t in poses]).reshape(-1, 3),
    )


def track_observations(reconstruction: pycolmap.Reconstruction, names: Sequence[str]) -> Observations:
    """The 3D points each of the images ``names`` observes, from the model's tracks."""
    row_of_id = {image.image_id: row for row, image in enumerate(reconstruction.find_image_with_name(n) for n in names)}
    rows, columns = [], []
    for column, point in enumerate(reconstruction.points3D.values()):
        for element in point.track.elements:
            row = row_of_id.get(element.image_id)
            if row is not None:
                rows.append(row)
                columns.append(column)
    incidence = sparse.csr_matrix(
        (np.ones(len(rows), dtype=bool), (rows, columns)), shape=(len(names), reconstruction.num_points3D())
    )
    incidence.sum_duplicates()  # a point observed twice in one image counts once
    return Observations(list(names), incidence)
