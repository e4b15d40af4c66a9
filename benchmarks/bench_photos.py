"""``data=photos`` on photos with known poses: how close pycolmap's reconstruction comes to them.

    .venv/bin/python benchmarks/bench_photos.py KAPTURE [KAPTURE ...] [--root DIR] [--overrides key=value ...]

Copies the images of the kapture folders (mapping and query alike; their poses withheld) into a
temporary photo folder, reconstructs it as ``python evaluate.py data=photos`` does (the overrides
are Hydra's, e.g. ``data.reconstruction.matching=sequential data.unitless=true``), aligns the
recovered camera centres to the known ones with a similarity (pycolmap's ``estimate_sim3d``) and
prints the registered share, the time, the centre errors after the alignment (in the known poses'
units and as a share of the scene's extent) and the errors of the relative rotations of every pair.
With ``--root`` the photo folder (``DIR/photos``) and the cache (``DIR/.cache``) are kept:
``python evaluate.py data=photos data.images=DIR/photos paths.root_dir=DIR ...`` then benchmarks the
cached reconstruction.
"""

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval import geometry
from locretrieval.build import scene_of
from locretrieval.scene.kapture_io import concatenate_image_sets, load_image_set

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("kapture", nargs="+", type=Path, help="kapture folders with known poses")
    parser.add_argument("--root", type=Path, help="folder kept for the photos and the cache (default: temporary)")
    parser.add_argument("--overrides", nargs="*", default=[], help="Hydra overrides of evaluate.py")
    arguments = parser.parse_args()
    known = concatenate_image_sets([load_image_set(folder) for folder in arguments.kapture])
    with tempfile.TemporaryDirectory(prefix="bench_photos-") as temporary:
        root = arguments.root or Path(temporary)
        photos = root / "photos"
        for name, path in zip(known.names, known.paths):
            (photos / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, photos / name)
        overrides = ["data=photos", f"data.images={photos}", f"paths.root_dir={root}", *arguments.overrides]
        with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
            cfg = compose("evaluate", overrides=overrides)
        started, cpu = time.perf_counter(), time.process_time()
        scene = scene_of(cfg.data)
        seconds = (time.perf_counter() - started, time.process_time() - cpu)
    images = concatenate_image_sets([scene.database, scene.queries])
    rows = [known.names.index(name) for name in images.names]
    report(scene.quality, seconds, images, known.subset(np.array(rows)), len(known))


def report(quality, seconds: tuple[float, float], recovered, known, photos: int) -> None:
    """Print the registered share, the time and the errors after a similarity alignment."""
    import pycolmap

    print(f"{quality.describe()}")
    wall, cpu = seconds
    print(f"reconstruction and loading: {wall:.1f} s ({cpu:.1f} s of CPU, every thread) for {photos} photos")
    known_from_recovered = pycolmap.estimate_sim3d(recovered.centers, known.centers)
    matrix = np.asarray(known_from_recovered.matrix())
    aligned = recovered.centers @ matrix[:, :3].T + matrix[:, 3]
    errors = np.linalg.norm(aligned - known.centers, axis=1)
    extent = float(np.linalg.norm(known.centers.max(axis=0) - known.centers.min(axis=0)))
    angles = relative_rotation_errors(recovered.qvec, known.qvec)
    print(
        f"centre error after alignment (known units): median {np.median(errors):.3f}, "
        f"90 % {np.quantile(errors, 0.9):.3f}, max {errors.max():.3f} ({100 * np.median(errors) / extent:.2f} % / "
        f"{100 * errors.max() / extent:.2f} % of the {extent:.1f} extent)"
    )
    print(f"relative rotation error of every pair (deg): median {np.median(angles):.3f}, max {angles.max():.3f}")


def relative_rotation_errors(recovered: np.ndarray, known: np.ndarray) -> np.ndarray:
    """The angle (degrees) between the recovered and the known rotation from camera i to camera j, every
    pair i < j: free of the alignment (whose rotation a straight trajectory leaves loose about its line)."""
    first, second = np.triu_indices(len(known), k=1)

    def relative(q: np.ndarray) -> np.ndarray:
        return geometry.quaternion_multiply(q[second], geometry.quaternion_conjugate(q[first]))

    return geometry.rotation_errors_deg(relative(recovered), relative(known))


if __name__ == "__main__":
    main()
