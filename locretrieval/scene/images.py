"""Reading image files with errors that name the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError


def read_image(path: str | Path, grayscale: bool = False) -> np.ndarray:
    """``uint8`` array ``[H, W, 3]`` (RGB) or ``[H, W]`` (grayscale) of an image file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image file not found: {path}")
    try:
        with Image.open(path) as image:
            return np.asarray(image.convert("L" if grayscale else "RGB"))
    except (UnidentifiedImageError, OSError) as error:
        raise ValueError(f"cannot decode image file {path}: {error}") from error
