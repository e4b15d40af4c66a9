"""Miniatures of the published datasets' folder trees as NAVER's downloader installs them."""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import kapture
import kapture.io.csv as kapture_csv
import numpy as np
from PIL import Image

from locretrieval.scene import ImageSet

SCENE = {"width": 192, "height": 144, "num_database": 12, "num_queries": 4, "texture_size": 64, "length": 20.0,
         "conditions": {"night": 0.0, "blur": 0.0, "dynamic": 0.0, "noise": 0.0}, "database_dynamic": 0.0,
         "hard_query_fraction": 0.0, "workers": 1, "seed": 4}  # fmt: skip
R2D2 = "r2d2_WASF-N8_20k"
GLOBAL_DIMENSION = 48


@dataclass(frozen=True)
class Layout:
    """Where a dataset's kapture folders and features are, relative to the data root:
    ``mapping``/``queries`` folders with the image names they get (``{i}``: a counter),
    which query folders have poses, the folder holding ``global_features``/``local_features``
    for each kapture folder, and where the images are when the kapture folders link their
    ``records_data`` there (RobotCar v1, published without images)."""

    mapping: dict[str, str]
    queries: dict[str, str]
    posed_queries: tuple[str, ...]
    feature_name: str
    shared_images: str | None = None

    def feature_root(self, folder: str) -> str:
        return str(Path(folder).parent)


LAYOUTS = {
    "aachen": Layout(
        {"Aachen-Day-Night-v1.1/mapping": "db/{i}.jpg"},
        {
            "Aachen-Day-Night-v1.1/query_day": "query/day/milestone/2010-10-30_17-47-25_{i}.jpg",
            "Aachen-Day-Night-v1.1/query_night": "query/night/nexus5x/IMG_20161227_19{i:04d}.jpg",
        },
        (),
        "AP-GeM-LM18",
    ),
    "baidu": Layout(
        {"baidu-mall/mapping": "training_images_undistort/00/nikon5300a_{i:04d}.jpg"},
        {"baidu-mall/query": "query_images_undistort/cdm/cdm_20150523_10{i:04d}.jpg"},
        ("baidu-mall/query",),
        "densevlad_multi",
    ),
    "robotcar": Layout(
        {"RobotCar_Seasons-v1/mapping": "overcast-reference/rear/14171765{i:08d}.jpg"},
        {"RobotCar_Seasons-v1/query": "night/rear/14184{i:08d}.jpg"},
        ("RobotCar_Seasons-v1/query",),
        "netvlad_vd16pitts",
        shared_images="RobotCar_Seasons-v2/all/sensors/records_data",
    ),
    "robotcar_v2": Layout(
        {
            "RobotCar_Seasons-v2/01/mapping": "overcast-reference/rear/14171765{i:08d}.jpg",
            "RobotCar_Seasons-v2/02/mapping": "overcast-reference/rear/14171766{i:08d}.jpg",
        },
        {
            "RobotCar_Seasons-v2/01/query": "night/rear/14184{i:08d}.jpg",
            "RobotCar_Seasons-v2/02/query": "dawn/rear/14168{i:08d}.jpg",
        },
        (),
        "netvlad_vd16pitts",
    ),
    "gangnam": Layout(
        {"GangnamStation/B2/release/mapping": "10004/images/{i:06d}.jpg"},
        {
            "GangnamStation/B2/release/validation": "10005/images/{i:06d}.jpg",
            "GangnamStation/B2/release/test": "10006/images/{i:06d}.jpg",
        },
        ("GangnamStation/B2/release/validation",),
        "DELG",
    ),
    "inloc": Layout(
        {"InLoc/mapping": "DUC1/024/DUC_cutout_024_{i}_0.jpg"},
        {"InLoc/query": "iphone7/IMG_{i:04d}.JPG"},
        (),
        "AP-GeM-LM18",
    ),
}


def split(count: int, parts: int) -> list[np.ndarray]:
    return np.array_split(np.arange(count), parts)


def write_kapture_folder(root: Path, images: ImageSet, rows: np.ndarray, pattern: str, posed: bool) -> dict[str, str]:
    """A kapture folder of ``images[rows]`` renamed by ``pattern`` and saved as JPEG, written by
    the kapture library; returns new name -> source name."""
    data = kapture.Kapture(
        sensors=kapture.Sensors(),
        records_camera=kapture.RecordsCamera(),
        trajectories=kapture.Trajectories() if posed else None,
    )
    names = {}
    for timestamp, row in enumerate(rows):
        camera = images.cameras[row]
        sensor = f"cam{timestamp}"
        data.sensors[sensor] = kapture.Camera(camera.model, [camera.width, camera.height, *camera.params])
        name = pattern.format(i=timestamp)
        data.records_camera[(timestamp, sensor)] = name
        if posed:
            data.trajectories[(timestamp, sensor)] = kapture.PoseTransform(
                r=images.qvec[row].tolist(), t=images.tvec[row].tolist()
            )
        path = root / "sensors" / "records_data" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.open(images.paths[row]).convert("RGB").save(path, quality=95)
        names[name] = images.names[row]
    kapture_csv.kapture_to_dir(str(root), data)
    return names


def write_features(
    feature_root: Path, feature_name: str, names: dict[str, str], local: dict, images: dict[str, Path]
) -> None:
    """Global features (a unit thumbnail per image) and the local features as R2D2 files, in the
    downloader's layout under ``feature_root``."""
    global_folder = feature_root / "global_features" / feature_name / "global_features"
    keypoints_folder = feature_root / "local_features" / R2D2 / "keypoints"
    descriptors_folder = feature_root / "local_features" / R2D2 / "descriptors"
    headers = {
        global_folder / "global_features.txt": f"{feature_name}, float32, {GLOBAL_DIMENSION}, L2",
        keypoints_folder / "keypoints.txt": f"{R2D2}, float32, 2",
        descriptors_folder / "descriptors.txt": f"{R2D2}, float32, 128, {R2D2}, L2",
    }
    for path, line in headers.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(f"# kapture format: 1.1\n{line}\n")
    for name, source in names.items():
        thumbnail = np.asarray(Image.open(images[source]).convert("L").resize((8, 6)), dtype=np.float32).ravel()
        thumbnail -= thumbnail.mean()
        keypoints, descriptors = local[source]
        arrays = {
            global_folder / f"{name}.gfeat": thumbnail / np.linalg.norm(thumbnail),
            keypoints_folder / f"{name}.kpt": keypoints - 0.5,  # R2D2's pixel centres start at (0, 0)
            descriptors_folder / f"{name}.desc": descriptors / np.linalg.norm(descriptors, axis=1, keepdims=True),
        }
        for path, array in arrays.items():
            path.parent.mkdir(parents=True, exist_ok=True)
            np.ascontiguousarray(array, dtype=np.float32).tofile(path)


def install(layout: Layout, rendered, data_dir: Path) -> None:
    scene, local = rendered
    sources = {
        **dict(zip(scene.database.names, scene.database.paths)),
        **dict(zip(scene.queries.names, scene.queries.paths)),
    }
    groups = [
        (folder, pattern, scene.database, rows, True)
        for (folder, pattern), rows in zip(layout.mapping.items(), split(len(scene.database), len(layout.mapping)))
    ]
    groups += [
        (folder, pattern, scene.queries, rows, folder in layout.posed_queries)
        for (folder, pattern), rows in zip(layout.queries.items(), split(len(scene.queries), len(layout.queries)))
    ]
    for folder, pattern, images, rows, posed in groups:
        names = write_kapture_folder(data_dir / folder, images, rows, pattern, posed)
        write_features(data_dir / layout.feature_root(folder), layout.feature_name, names, local, sources)
        if layout.shared_images:
            records = data_dir / folder / "sensors" / "records_data"
            shutil.copytree(records, data_dir / layout.shared_images, dirs_exist_ok=True)
            shutil.rmtree(records)
            records.symlink_to(os.path.relpath(data_dir / layout.shared_images, records.parent))
