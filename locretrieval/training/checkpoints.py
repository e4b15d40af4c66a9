"""Lightning checkpoints of train.py: checked before a run resumes from one."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from locretrieval.models.weights import EMBEDDED_CHECKPOINT_KEY, check_checkpoint, load_torch_file


def check_resume_checkpoint(path: str | os.PathLike, model: str, architecture: Mapping[str, Any]) -> None:
    """Raise, naming ``ckpt_path``, unless ``path`` is a Lightning checkpoint written by train.py
    for ``model`` with ``architecture``. Read with the restricted unpickler: a file that is not a
    checkpoint is never unpickled by anything else."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"ckpt_path: {path} not found (a checkpoint of train.py, e.g. <run>/checkpoints/last.ckpt)")
    try:
        content = load_torch_file(path)
    except ValueError as error:
        raise ValueError(f"ckpt_path: {path} is not a Lightning checkpoint of locretrieval's train.py ({error})") from None
    if not isinstance(content, Mapping) or EMBEDDED_CHECKPOINT_KEY not in content or "state_dict" not in content:
        raise ValueError(f"ckpt_path: {path} is a PyTorch file but not a Lightning checkpoint of locretrieval's train.py "
                         f"(it has no {EMBEDDED_CHECKPOINT_KEY!r} and 'state_dict' entries)")
    try:
        check_checkpoint(content[EMBEDDED_CHECKPOINT_KEY], path, model, architecture)
    except ValueError as error:
        raise ValueError(f"ckpt_path: {error}; resume with the model settings of the run that wrote it") from None
