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

from locretrieval import limits
from locretrieval.errors import FIX_DATA_FILE, DataFileError
from locretrieval.folders import inside, walk

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
            check_pixels(path, image.size)
            if max_side is None:
                return np.asarray(image.convert(mode))
            image.draft(mode, (max_side, max_side))  # JPEG: DCT scaling to >= the size asked; others: no-op
            image = image.convert(mode)
            image.thumbnail((max_side, max_side), Image.Resampling.LANCZOS)
            return np.asarray(image)
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as error:
        raise DataFileError(path, f"cannot decode this image file ({error})", FIX_DATA_FILE) from None


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an image file, from its header, within ``limits.image_pixels``
    (`check_pixels`); a `DataFileError` naming it when unreadable."""
    try:
        with Image.open(path) as image:
            size = image.size
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as error:
        raise DataFileError(path, f"not a readable image ({error})", FIX_DATA_FILE) from None
    check_pixels(path, size)
    return size


def check_pixels(path: Path, size: tuple[int, int]) -> None:
    """Raise a `DataFileError` naming the image ``path`` when its ``(width, height)`` (its header's)
    holds more than ``limits.image_pixels`` pixels: decoding it and extracting its features take
    about 12 bytes a pixel (a 164 KB PNG of 13,000 x 13,000 zeros took 2.1 GB)."""
    most = limits.current().image_pixels
    if size[0] * size[1] > most:
        raise DataFileError(
            path,
            f"{size[0]} x {size[1]} = {size[0] * size[1]} pixels, more than {most} (limits.image_pixels; refused "
            "before decoding it): shrink the image, or raise the limit for larger images",
        )


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
    ``/``-separated names relative to it, walked safely (`locretrieval.folders.walk`: a link to a
    folder inside is not followed, a folder is walked once, at most ``limits.folder_entries``
    entries). Images resolving outside the folder (a link to a file, or files below a link to a
    folder) are logged once, or refused with ``limits.outside_images: refuse`` (`check_inside`).
    Hidden files and folders are skipped; other files and the links not followed are logged."""
    refuse = limits.current().outside_images == "refuse"
    names, others, not_followed = [], [], []
    for entry in walk(folder, hidden=False, follow_outside=not refuse):
        if entry.is_dir:
            if entry.outside and refuse:
                raise _outside(Path(entry.path), entry.target, "image folder", folder, "a folder")
            if entry.target is not None and not entry.outside:
                not_followed.append(entry.name)
        elif Path(entry.name).suffix.lower() in IMAGE_EXTENSIONS:
            names.append(entry.name)
        else:
            others.append(entry.name)
    if others:
        log.warning(
            "%s: %d files are not images %s and are left out, e.g. %s",
            folder,
            len(others),
            IMAGE_EXTENSIONS,
            others[:3],
        )
    if not_followed:
        log.warning(
            "%s: %d links to folders inside it are not followed (their images are listed where they are), e.g. %s",
            folder,
            len(not_followed),
            not_followed[:3],
        )
    names.sort()
    check_inside(folder, folder, names, "image folder")
    return names


def check_inside(root: Path, image_root: Path, names: Sequence[str], kind: str) -> None:
    """Images of ``image_root`` (``names``) whose files resolve (through symbolic links) outside the
    ``kind`` of folder ``root`` (a kapture folder, an image folder): logged once (datasets link their
    images from shared storage), refused with ``limits.outside_images: refuse``."""
    outside = [
        (name, resolved)
        for name in names
        if not inside(resolved := os.path.realpath(os.path.join(image_root, name)), root)
    ]
    if not outside:
        return
    name, resolved = outside[0]
    if limits.current().outside_images == "refuse":
        raise _outside(image_root / name, resolved, kind, root, f"{len(outside)} of its {len(names)} images do")
    log.warning(
        "%s: %d of %d images resolve outside the folder (symbolic links), e.g. %s -> %s; "
        "limits.outside_images=refuse refuses such folders",
        root,
        len(outside),
        len(names),
        name,
        resolved,
    )


def _outside(path: Path, resolved: str | None, kind: str, root: Path, detail: str) -> DataFileError:
    return DataFileError(
        path, f"resolves to {resolved}, outside the {kind} {root} (limits.outside_images: refuse); {detail}"
    )


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
