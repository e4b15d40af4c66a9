"""Lightning checkpoints of train.py: written atomically, checked before a run resumes from one."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO

from locretrieval.cache import atomic_path
from locretrieval.models.files.weights import EMBEDDED_CHECKPOINT_KEY, check_checkpoint, load_torch_file


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint writer, made atomic on local paths: the checkpoint is written to a
    temporary file beside its target and renamed over it (`atomic_path`), so a run killed while
    writing ``last.ckpt`` leaves the previous one whole. (Lightning's own writer stages the file in
    the system temporary folder and moves it into place, which is a non-atomic copy whenever that
    folder is on another file system than the run's.)"""

    def save_checkpoint(
        self, checkpoint: dict[str, Any], path: str | os.PathLike, storage_options: Any | None = None
    ) -> None:
        if storage_options is not None or "://" in str(path):  # remote storage: Lightning's own writer
            return super().save_checkpoint(checkpoint, path, storage_options)
        with atomic_path(path) as temporary:
            torch.save(checkpoint, temporary)


def check_resume_checkpoint(path: str | os.PathLike, model: str, architecture: Mapping[str, Any]) -> None:
    """Raise, naming ``ckpt_path``, unless ``path`` is a Lightning checkpoint written by train.py
    for ``model`` with ``architecture``. Read with the restricted unpickler: a file that is not a
    checkpoint is never unpickled by anything else."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"ckpt_path: {path} not found (a checkpoint of train.py, e.g. <run>/checkpoints/last.ckpt)"
        )
    try:
        content = load_torch_file(path)
    except ValueError as error:
        raise ValueError(
            f"ckpt_path: {path} is not a Lightning checkpoint of locretrieval's train.py ({error})"
        ) from None
    if not isinstance(content, Mapping) or EMBEDDED_CHECKPOINT_KEY not in content or "state_dict" not in content:
        raise ValueError(
            f"ckpt_path: {path} is a PyTorch file but not a Lightning checkpoint of locretrieval's train.py "
            f"(it has no {EMBEDDED_CHECKPOINT_KEY!r} and 'state_dict' entries)"
        )
    try:
        check_checkpoint(content[EMBEDDED_CHECKPOINT_KEY], path, model, architecture)
    except ValueError as error:
        raise ValueError(f"ckpt_path: {error}; resume with the model settings of the run that wrote it") from None
