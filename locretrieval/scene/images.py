"""Reading image files with errors that name the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from locretrieval.errors import FIX_DATA_FILE, DataFileError


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
