"""Small networks and train.py's checkpoints of them, for the tests of the exports (support module)."""

from pathlib import Path

import helpers
import numpy as np
import torch
from hydra.utils import instantiate

from locretrieval.models.files.weights import EMBEDDED_CHECKPOINT_KEY, load_torch_file


def lightning_checkpoint(descriptor, path: Path) -> Path:
    """``descriptor``'s network as train.py's Lightning checkpoint embeds it (`EMBEDDED_CHECKPOINT_KEY`)."""
    plain = path.with_suffix(".plain")
    descriptor.save_checkpoint(plain)
    torch.save({EMBEDDED_CHECKPOINT_KEY: load_torch_file(plain), "state_dict": {}, "epoch": 3}, path)
    return path


def descriptors(model, images: torch.Tensor) -> np.ndarray:
    """The model's own descriptors of a normalised batch (one scale, then its final projection)."""
    with torch.no_grad():
        return model.network.finalize(model.network.eval()(images)).numpy()


def small_model(pooling: str):
    """A random network on timm's test ResNet with ``pooling``, 128 px."""
    cfg = helpers.evaluate_config(
        "model=timm", "model.name=test_resnet", f"model/pooling={pooling}", "model.random_init=true",
        "model.max_side=128", *helpers.QUIET_EXTRACTION,
    )  # fmt: skip
    return instantiate(cfg.model)
