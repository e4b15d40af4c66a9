"""A folder of photos as a benchmark (``data=photos``): pycolmap reconstructs them (SIFT features,
matching, incremental mapping) into the run's cache, as Aachen's and InLoc's reference poses were
made, and the largest model is read as a COLMAP model (`locretrieval.scene.colmap`).

The reconstruction is cached under ``<cache_dir>/photos/<key>/`` (`reconstruction_folders`): a
database of features and matches keyed by the images (names, sizes, modification times), their
settings, the device and pycolmap's version, and below it a folder per mapping's settings. Each
stage resumes where an interrupted run left it: features already in the database are not
extracted again, pairs already matched are not matched again, and the model is written once
mapping is done. Every stage shows its progress.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from filelock import FileLock
from PIL import ExifTags, Image
from tqdm import tqdm

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval.cache import atomic_path, config_key, file_signature, temporary_folder
from locretrieval.config import require, validated
from locretrieval.errors import DELETE_CACHE_FILE, DataFileError
from locretrieval.scene.colmap import SceneOptions, read_model, reconstruction_scene
from locretrieval.scene.images import IMAGE_EXTENSIONS, check_distinct_images, check_names, image_files, image_size
from locretrieval.scene.types import CAMERA_MODEL_PARAMS, CAMERA_MODELS, Scene

log = logging.getLogger(__name__)

#: Bump when what the cached reconstruction holds changes.
CACHE_VERSION = 1
#: How the images are paired for matching (``data.reconstruction.matching``).
MATCHING = ("auto", "exhaustive", "sequential", "spatial", "vocabtree")
#: Which images share a camera (``data.reconstruction.camera_mode``, COLMAP's camera modes).
CAMERA_MODES = ("auto", "single", "per_folder", "per_image")
#: Images per call of pycolmap's feature extraction, pairs per call of its matching (a step of the progress bars).
IMAGES_PER_STEP = 32
PAIRS_PER_STEP = 1000
#: The files of a reconstruction in its cache folder: the database, the mark of its matching done, and
#: in each mapping's folder the largest model and the number of images of every model (the mark of its end).
DATABASE_FILE, MATCHED_FILE, MODEL_DIR, MODELS_FILE = "database.db", "matched.txt", "model", "models.json"
#: The settings of the mapping alone (`reconstruction_folders`).
MAPPING_KEYS = ("init_min_tri_angle",)


@dataclass
class ReconstructionSettings:
    """How pycolmap reconstructs the photos (``data.reconstruction``): ``matching`` pairs (one of
    `MATCHING`; ``auto``: every pair up to ``exhaustive_max_images`` images, else the
    ``spatial_neighbours`` nearest by the photos' GPS, else the vocabulary tree ``vocab_tree``),
    ``sequential_overlap`` (the following images each frame of a video is matched with), the cameras
    (``camera_mode``, one of `CAMERA_MODES`: ``auto`` shares one camera among the photos of the same
    EXIF make, model, focal length and size; ``camera_model``, a COLMAP model; ``camera_params``, its
    parameters in pixels when they are known, a starting point refined by the mapping: frames of a
    video have no EXIF focal length, and the default guess, 1.2 x the longer side, can keep a
    forward-moving sequence from initializing), SIFT's
    ``max_image_size`` (pixels, longer side), ``max_num_features`` and ``first_octave`` (-1 doubles the
    image first: more features in small images), the mapping's ``init_min_tri_angle`` (degrees: the
    triangulation angle its first pair needs; forward-moving frames see small ones), ``min_registered``
    (fewer registered images are an error), the ``seed`` and the ``device`` (``auto``: pycolmap's GPU
    where it has one)."""

    matching: str
    exhaustive_max_images: int
    sequential_overlap: int
    spatial_neighbours: int
    vocab_tree: str | None
    camera_mode: str
    camera_model: str
    camera_params: list[float] | None
    max_image_size: int
    max_num_features: int
    first_octave: int
    init_min_tri_angle: float
    min_registered: int
    seed: int
    device: str

    def __post_init__(self) -> None:
        require(self.matching in MATCHING, "matching", f"must be one of {list(MATCHING)}, got {self.matching!r}")
        require(self.camera_mode in CAMERA_MODES, "camera_mode", f"must be one of {list(CAMERA_MODES)}")
        require(
            self.camera_model in CAMERA_MODELS,
            "camera_model",
            f"must be a COLMAP model locretrieval reads: {sorted(CAMERA_MODELS)}, got {self.camera_model!r}",
        )
        expected = CAMERA_MODEL_PARAMS.get(self.camera_model)
        require(
            self.camera_params is None or len(self.camera_params) == expected,
            "camera_params",
            f"{self.camera_model} takes {expected} parameters, got {self.camera_params}",
        )
        for key in ("exhaustive_max_images", "sequential_overlap", "spatial_neighbours", "max_image_size"):
            require(getattr(self, key) >= 1, key, f"must be >= 1, got {getattr(self, key)}")
        require(self.max_num_features >= 16, "max_num_features", f"must be >= 16, got {self.max_num_features}")
        require(self.first_octave in (-1, 0, 1), "first_octave", f"must be -1, 0 or 1, got {self.first_octave}")
        require(
            0 < self.init_min_tri_angle < 90,
            "init_min_tri_angle",
            f"must be degrees in (0, 90), got {self.init_min_tri_angle}",
        )
        require(self.min_registered >= 3, "min_registered", f"must be >= 3 images, got {self.min_registered}")
        require(self.device in ("auto", "cpu", "cuda"), "device", f"must be auto, cpu or cuda, got {self.device!r}")
        require(
            self.matching != "vocabtree" or self.vocab_tree is not None,
            "vocab_tree",
            "matching=vocabtree needs the path of a COLMAP vocabulary tree file (nothing is downloaded)",
        )

    def pycolmap_device(self) -> Any:
        """pycolmap's device: its GPU when it was built with CUDA and ``device`` allows it."""
        import pycolmap

        if self.device == "cuda" and not pycolmap.has_cuda:
            raise RuntimeError("data.reconstruction.device=cuda but this pycolmap has no CUDA; use auto or cpu")
        return pycolmap.Device.cuda if self.device != "cpu" and pycolmap.has_cuda else pycolmap.Device.cpu


def load_photos_dataset(
    name: str, root: str | Path, images: str | Path, cache_dir: str | Path, *, reconstruction: Any, **options: Any
) -> Scene:
    """The `Scene` of a folder of photos (``images``, relative to ``root`` or absolute; subfolders
    are sequences), reconstructed by pycolmap as ``reconstruction`` (`ReconstructionSettings`) into
    ``cache_dir`` and read as a COLMAP model; the other keys of its ``data`` node are its
    `SceneOptions` (`SCENE_KEYS`), as ``data=colmap``'s. Bad input is refused before any
    reconstruction: an empty folder, an unreadable or a duplicated image."""
    from locretrieval.scene.datasets import DatasetNotFoundError

    scene = SceneOptions.from_keys(name, options)
    settings = validated(ReconstructionSettings, reconstruction, "data.reconstruction")
    folder = Path(root).expanduser() / images
    if not folder.is_dir():
        raise DatasetNotFoundError(
            f"photo folder not found: {folder}\ndata.images is a folder of photos (subfolders are sequences); "
            f"relative paths start at the data root {root} ($LOCRETRIEVAL_DATA or paths.data_dir)."
        )
    names = checked_photos(folder)
    model = reconstruct(folder, names, settings, Path(cache_dir))
    return reconstruction_scene(read_model(model), str(model), folder, scene)


def checked_photos(folder: Path) -> list[str]:
    """The images of ``folder``, each readable and none a copy of another."""
    names = image_files(folder)
    if not names:
        extensions = ", ".join(IMAGE_EXTENSIONS)
        raise DataFileError(folder, f"no image files (extensions {extensions}, any case) to reconstruct")
    check_names(folder, names)
    for name in names:
        image_size(folder / name)  # its header: an unreadable file is named now, not inside pycolmap
    check_distinct_images(folder, names)
    return names


def reconstruct(folder: Path, names: Sequence[str], settings: ReconstructionSettings, cache_dir: Path) -> Path:
    """The folder of the model pycolmap reconstructed from the images ``names`` of ``folder``: the
    largest of its models (cached, `reconstruction_folders`); raises when it registers fewer than
    ``settings.min_registered`` images."""
    import pycolmap

    device = settings.pycolmap_device()
    work, mapping = reconstruction_folders(folder, names, settings, device.name, cache_dir)
    work.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(work.parent / f".{work.name}.lock"):  # one process reconstructs, the others wait for it
        if (mapping / MODELS_FILE).is_file():
            log.info("reconstruction of %s cached in %s", folder, mapping)
        else:
            work.mkdir(exist_ok=True)
            log.info("reconstructing %d photos of %s with pycolmap (%s) into %s", len(names), folder, device.name, work)
            pycolmap.logging.minloglevel = 2  # its progress is ours
            database = work / DATABASE_FILE
            if not (work / MATCHED_FILE).is_file():
                extract(folder, names, settings, database, device)
                match(database, settings, device)
                with atomic_path(work / MATCHED_FILE) as path:
                    path.write_text("features and matches of every pair are in the database\n")
            build_models(folder, names, database, settings, mapping)
    sizes = read_models_file(mapping / MODELS_FILE)
    registered = max(sizes, default=0)
    if registered < settings.min_registered:
        raise ValueError(
            f"pycolmap registered {registered} of the {len(names)} images of {folder} "
            f"({len(sizes)} model(s) of {sorted(sizes, reverse=True)} images; at least "
            f"data.reconstruction.min_registered={settings.min_registered} needed): too few overlapping images to "
            "reconstruct. Photos of one place taken a few steps apart, each sharing much of its view with others, "
            "reconstruct; data.reconstruction.matching=exhaustive matches every pair; frames of a forward-moving "
            "video may need their camera_params and a smaller init_min_tri_angle"
        )
    if len(sizes) > 1:
        log.warning(
            "pycolmap made %d models of %s (%s images): the largest is the scene, the images of the others are "
            "left out (more overlapping photos would join them)",
            len(sizes),
            folder,
            sorted(sizes, reverse=True),
        )
    return mapping / MODEL_DIR


def reconstruction_folders(
    folder: Path, names: Sequence[str], settings: ReconstructionSettings, device: str, cache_dir: Path
) -> tuple[Path, Path]:
    """``<cache_dir>/photos/<key>``, the database of features and matches, and its subfolder
    ``mapping-<key>``, the models: the first key hashes the images (names, sizes, modification
    times), the settings of the features and the matching, the device as resolved and pycolmap's
    version; the second the settings of the mapping (another mapping of the same photos reuses
    their features and matches)."""
    import pycolmap

    images = [(name, *file_signature(folder / name)) for name in names]
    record = {**dataclasses.asdict(settings), "device": device}
    del record["min_registered"]  # a check of the result, not a setting of the reconstruction
    mapping = {key: record.pop(key) for key in MAPPING_KEYS}
    work = cache_dir / "photos" / config_key(CACHE_VERSION, record, pycolmap.__version__, images)
    return work, work / f"mapping-{config_key(mapping, record['seed'])}"


def extract(folder: Path, names: Sequence[str], settings: ReconstructionSettings, database: Path, device: Any) -> None:
    """SIFT features of every image into ``database``; images are imported first (their cameras
    from EXIF or the size, as ``camera_mode`` groups them), then extracted a step at a time
    (images with features already are skipped by pycolmap: an interrupted run resumes)."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = settings.camera_model
    if settings.camera_params is not None:
        reader.camera_params = ",".join(repr(float(value)) for value in settings.camera_params)
    options = pycolmap.FeatureExtractionOptions()
    options.max_image_size = settings.max_image_size
    options.sift.max_num_features = settings.max_num_features
    options.sift.first_octave = settings.first_octave
    pycolmap.Database.open(database).close()  # creates it
    if settings.camera_mode == "auto":  # one camera per group of photos (pycolmap's auto gives each its own)
        mode = pycolmap.CameraMode.SINGLE
        for group in camera_groups(folder, names):
            pycolmap.import_images(database, folder, mode, group, reader)  # images already there are kept
    else:
        mode = pycolmap.CameraMode.__members__[settings.camera_mode.upper()]
        pycolmap.import_images(database, folder, mode, list(names), reader)
    with tqdm(total=len(names), desc="photos: features", unit="image") as progress:
        for start in range(0, len(names), IMAGES_PER_STEP):
            step = list(names[start : start + IMAGES_PER_STEP])
            pycolmap.extract_features(database, folder, step, mode, reader, options, device)
            progress.update(len(step))


def camera_groups(folder: Path, names: Sequence[str]) -> list[list[str]]:
    """The photos grouped by the camera that took them: the same EXIF make, model and focal length
    and the same size (photos without EXIF: by size alone)."""
    groups: dict[tuple, list[str]] = {}
    for name in names:
        with Image.open(folder / name) as image:
            exif = image.getexif()
            focal = exif.get_ifd(ExifTags.IFD.Exif).get(ExifTags.Base.FocalLength)
            key = (exif.get(ExifTags.Base.Make), exif.get(ExifTags.Base.Model), str(focal), image.size)
        groups.setdefault(key, []).append(name)
    return list(groups.values())


def match(database: Path, settings: ReconstructionSettings, device: Any) -> None:
    """Match and verify the pairs `image_pairs` chooses, a step at a time (pairs matched already are
    skipped by pycolmap: an interrupted run resumes)."""
    import pycolmap

    pairs = image_pairs(database, settings)
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = settings.seed
    pairs_file = database.parent / "pairs.txt"
    pairing = pycolmap.ImportedPairingOptions(match_list_path=str(pairs_file))
    with tqdm(total=len(pairs), desc="photos: matching", unit="pair") as progress:
        for start in range(0, len(pairs), PAIRS_PER_STEP):
            step = pairs[start : start + PAIRS_PER_STEP]
            pairs_file.write_text("".join(f"{a} {b}\n" for a, b in step))  # the step's pairs, for pycolmap
            pycolmap.match_image_pairs(
                database, pairing_options=pairing, verification_options=verification, device=device
            )
            progress.update(len(step))


def image_pairs(database: Path, settings: ReconstructionSettings) -> list[tuple[str, str]]:
    """The image pairs to match, by name, from pycolmap's pair generator of ``settings.matching``
    (`matching_method` for ``auto``)."""
    import pycolmap

    db = pycolmap.Database.open(database)
    try:
        names = {image.image_id: image.name for image in db.read_all_images()}
        method = matching_method(settings, len(names), db.num_pose_priors())
        log.info("photos: %s matching of %d images", method, len(names))
        if method == "exhaustive":
            generator = pycolmap.ExhaustivePairGenerator(pycolmap.ExhaustivePairingOptions(), db)
        elif method == "sequential":
            options = pycolmap.SequentialPairingOptions(overlap=settings.sequential_overlap)
            generator = pycolmap.SequentialPairGenerator(options, db)
        elif method == "spatial":
            options = pycolmap.SpatialPairingOptions(max_num_neighbors=settings.spatial_neighbours)
            generator = pycolmap.SpatialPairGenerator(options, db)
        else:
            if not Path(settings.vocab_tree).is_file():
                raise FileNotFoundError(
                    f"data.reconstruction.vocab_tree: vocabulary tree {settings.vocab_tree} not found"
                )
            options = pycolmap.VocabTreePairingOptions(vocab_tree_path=settings.vocab_tree)
            generator = pycolmap.VocabTreePairGenerator(options, db)
        return [(names[a], names[b]) for a, b in generator.all_pairs()]
    finally:
        db.close()


def matching_method(settings: ReconstructionSettings, images: int, gps_images: int) -> str:
    """``settings.matching``, or for ``auto``: exhaustive up to ``exhaustive_max_images`` images,
    else spatial when every image has a GPS position, else the vocabulary tree when one is given."""
    if settings.matching != "auto" or images <= settings.exhaustive_max_images:
        return "exhaustive" if settings.matching == "auto" else settings.matching
    if gps_images == images:
        return "spatial"
    if settings.vocab_tree is not None:
        return "vocabtree"
    raise ValueError(
        f"{images} photos are more than data.reconstruction.exhaustive_max_images={settings.exhaustive_max_images} "
        f"to match every pair, and only {gps_images} have a GPS position for spatial matching: choose "
        "data.reconstruction.matching=sequential (frames of a video, in name order), give a COLMAP vocabulary tree "
        "file (data.reconstruction.vocab_tree), or raise exhaustive_max_images (the pairs grow as the square)"
    )


def build_models(
    folder: Path, names: Sequence[str], database: Path, settings: ReconstructionSettings, work: Path
) -> None:
    """Incremental mapping of the matched ``database``; the largest model goes to ``work/model`` and
    the number of images of every model to ``work/models.json`` (written last: the stage is done)."""
    work.mkdir(exist_ok=True)
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = settings.seed
    options.mapper.init_min_tri_angle = settings.init_min_tri_angle
    pycolmap.set_random_seed(settings.seed)
    with (
        temporary_folder(work, "mapping") as scratch,
        tqdm(total=len(names), desc="photos: mapping", unit="image") as progress,
    ):
        models = pycolmap.incremental_mapping(
            database,
            folder,
            scratch,
            options,
            initial_image_pair_callback=lambda: progress.update(2),  # each model starts from two images
            next_image_callback=lambda: progress.update(1),
        )
        sizes = sorted((model.num_reg_images() for model in models.values()), reverse=True)
        if models:
            largest = max(models.values(), key=lambda model: model.num_reg_images())
            target = work / MODEL_DIR
            shutil.rmtree(target, ignore_errors=True)
            staged = scratch / "largest"
            staged.mkdir()
            largest.write(staged)
            staged.replace(target)
    with atomic_path(work / MODELS_FILE) as path:
        path.write_text(json.dumps({"registered": sizes}))


def read_models_file(path: Path) -> list[int]:
    """The number of registered images of each model (`build_models`)."""
    try:
        sizes = json.loads(path.read_text())["registered"]
    except (ValueError, KeyError, TypeError) as error:
        raise DataFileError(path, f"not a reconstruction summary ({error})", DELETE_CACHE_FILE) from None
    return [int(size) for size in sizes]
