"""Reading image files and checking image folders, with errors that name the file."""

from __future__ import annotations

import hashlib
import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image, UnidentifiedImageError

from locretrieval.errors import FIX_DATA_FILE, DataFileError

if TYPE_CHECKING:
    from locretrieval.scene.types import Camera

log = logging.getLogger(__name__)

#: File name extensions (lower case) of the images a folder of photos is read for (those pycolmap decodes).
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")


def read_image(path: str | Path, grayscale: bool = False, max_side: int | None = None) -> np.ndarray:
    """``uint8`` array ``[H, W, 3]`` (RGB) or ``[H, W]`` (grayscale) of an image file; with
    ``max_side``, shrunk (aspect kept, never enlarged) to at most that many pixels on its longer
    side, JPEGs decoded at a reduced scale (a thumbnail at a fraction of a full decode's time)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image file not found: {path}")
    mode = "L" if grayscale else "RGB"
    try:
        with Image.open(path) as image:
            if max_side is None:
                return np.asarray(image.convert(mode))
            image.draft(mode, (max_side, max_side))  # JPEG: DCT scaling to >= the size asked; others: no-op
            image = image.convert(mode)
            image.thumbnail((max_side, max_side), Image.Resampling.LANCZOS)
            return np.asarray(image)
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as error:
        raise DataFileError(path, f"cannot decode this image file ({error})", FIX_DATA_FILE) from None


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an image file, from its header; a `DataFileError` naming it when unreadable."""
    try:
        with Image.open(path) as image:
            return image.size
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as error:
        raise DataFileError(path, f"not a readable image ({error})", FIX_DATA_FILE) from None


def check_image_sizes(folder: Path, names: Sequence[str], cameras: Sequence[Camera], where: Sequence[str]) -> None:
    """Raise unless every image file (its header only) has its camera's width and height: keypoints
    of a resized image would be read in the wrong pixel frame. ``where``: each camera's name and
    the file defining it, for the error."""
    for name, camera, camera_where in zip(names, cameras, where):
        path = folder / name
        size = image_size(path)
        if size != (camera.width, camera.height):
            raise DataFileError(
                path,
                f"image is {size[0]}x{size[1]} pixels but its camera {camera_where} is "
                f"{camera.width}x{camera.height}; resize the image or scale that camera's intrinsics to the image",
            )


def check_names(path: Path, names: Sequence[str]) -> None:
    """Image names are written space-separated in LTVL submissions (and COLMAP's pairs files):
    refuse whitespace at load time; ``path``: the file (or folder) listing them."""
    spaced = [name for name in names if any(character.isspace() for character in name)]
    if spaced:
        raise DataFileError(path, f"image names with whitespace cannot be exported for LTVL: {spaced[:3]}")


def image_files(folder: Path) -> list[str]:
    """The images of ``folder`` and its subfolders (`IMAGE_EXTENSIONS`, any case), as sorted
    ``/``-separated names relative to it; hidden files and folders are skipped and other files
    are logged as left out."""
    names, others = [], []
    for root, folders, files in os.walk(folder, followlinks=True):
        folders[:] = sorted(name for name in folders if not name.startswith("."))
        relative = Path(root).relative_to(folder)
        for file in files:
            if file.startswith("."):
                continue
            name = (relative / file).as_posix()
            (names if Path(file).suffix.lower() in IMAGE_EXTENSIONS else others).append(name)
    if others:
        log.warning(
            "%s: %d files are not images %s and are left out, e.g. %s",
            folder,
            len(others),
            IMAGE_EXTENSIONS,
            others[:3],
        )
    return sorted(names)


def check_distinct_images(folder: Path, names: Sequence[str]) -> None:
    """Raise when two image files have the same content (a copied photo would be its own nearest
    image at the same pose), naming both."""
    by_size: dict[int, list[str]] = {}
    for name in names:
        by_size.setdefault(os.path.getsize(folder / name), []).append(name)
    for same_size in by_size.values():
        if len(same_size) < 2:
            continue
        seen: dict[str, str] = {}
        for name in same_size:
            digest = hashlib.sha256((folder / name).read_bytes()).hexdigest()
            if digest in seen:
                raise DataFileError(
                    folder / name,
                    f"the same image as {folder / seen[digest]} (identical bytes); remove one of the copies",
                )
            seen[digest] = name
