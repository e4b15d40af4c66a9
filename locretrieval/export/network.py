"""A torch descriptor's network as other tools run it, and the ``locretrieval`` torch.hub entry point.

`DescriptorNetwork` maps a batch of images ``float32 [B, 3, H, W]``, RGB normalised as the model
expects (``(rgb / 255 - mean) / std``, its ``preprocessing.mean`` and ``.std``), to unit global
descriptors ``float32 [B, D]``: the network's single-scale forward pass, then its final projection
(``finalize``; the identity for every trainable model). Images are resized beforehand as
``preprocessing`` says (``max_side`` or ``size``, sides in steps of ``multiple_of``). A model that
sums several ``scales`` computes one here; the caller sums them, as torch.hub's descriptors of the
field leave preprocessing to the caller.

`descriptor_from_checkpoint` builds the descriptor a locretrieval checkpoint records (a Lightning
checkpoint of ``train.py``, or `TorchGlobalDescriptor.save_checkpoint`'s file) from the file alone:
its model, architecture and preprocessing (the ``max_side``, ``size``, ``scales``, ``mean`` and
``std`` it was trained at, as ``export.py`` and ``evaluate.py model=checkpoint`` take them), a file's
data whose every ``_target_`` is checked (`locretrieval.parts.check_recorded`) before anything it
names is imported. ``hubconf.py`` at the repository root exposes `locretrieval`:
``torch.hub.load(<repository>, "locretrieval", weights=<checkpoint>, source="local")``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch
from hydra.utils import get_class
from torch import nn

from locretrieval.models.extraction import ExtractionSettings, Preprocessing
from locretrieval.models.files.weights import embedded_checkpoint, is_checkpoint, load_torch_file
from locretrieval.models.networks import POOLING, upgrade_legacy_pooling
from locretrieval.models.torch_descriptor import TorchGlobalDescriptor
from locretrieval.models.trainable import FROM_CHECKPOINT
from locretrieval.models.trainable.backbones import BACKBONE, upgrade_legacy_backbone
from locretrieval.parts import check_recorded, refuse_interpolations

#: The model a checkpoint records -> the descriptor class that reads it (the trainable family).
CHECKPOINT_MODELS = {
    "trainable": "locretrieval.models.trainable.TrainableDescriptor",
    "dinov2": "locretrieval.models.trainable.dinov2.DinoV2Descriptor",
    "salad": "locretrieval.models.trainable.dinov2.SALADDescriptor",
    "boq": "locretrieval.models.trainable.dinov2.BoQDescriptor",
    "megaloc": "locretrieval.models.trainable.dinov2.MegaLocDescriptor",
}
#: How a network built from a checkpoint alone runs: on the CPU, in this process.
CPU_EXTRACTION = ExtractionSettings(
    device="cpu", batch_size=1, num_workers=0, mixed_precision=False, progress=False, memmap_dir=None
)


class DescriptorNetwork(nn.Module):
    """``network.finalize(network(images))``: normalised images ``[B, 3, H, W]`` to unit descriptors
    ``[B, D]`` (see the module's docstring); ``preprocessing`` says how images become its input."""

    def __init__(self, network: nn.Module, preprocessing: Preprocessing) -> None:
        super().__init__()
        self.network = network
        self.preprocessing = preprocessing
        self.output_dim = int(network.output_dim)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.network.finalize(self.network(images))


def descriptor_from_checkpoint(
    path: str | os.PathLike,
    max_side: int | str | None = FROM_CHECKPOINT,
    size: tuple[int, int] | str | None = FROM_CHECKPOINT,
    scales: tuple[float, ...] | str = FROM_CHECKPOINT,
) -> TorchGlobalDescriptor:
    """The descriptor a locretrieval checkpoint ``path`` records (`CHECKPOINT_MODELS`), built with the
    architecture and preprocessing it holds and filled with its weights, on the CPU; ``max_side``,
    ``size`` or ``scales`` given override the trained ones (logged when they differ). The file is read
    with the restricted unpickler; what is not such a checkpoint is a ``ValueError`` naming it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"weights: {path} not found (a locretrieval checkpoint, e.g. <run>/checkpoints/last.ckpt)"
        )
    content = embedded_checkpoint(load_torch_file(path))
    if not is_checkpoint(content):
        raise ValueError(
            f"{path}: not a locretrieval checkpoint (a Lightning checkpoint of train.py, or a file of "
            "TorchGlobalDescriptor.save_checkpoint)"
        )
    model = content.get("model")
    if model not in CHECKPOINT_MODELS:
        raise ValueError(
            f"{path}: a checkpoint of model {model!r}; the hub entry builds {sorted(CHECKPOINT_MODELS)} "
            "(export the others with export.py and their model=<name> config)"
        )
    architecture: dict[str, Any] = dict(content["architecture"])
    # data, not code: what it names checked before anything of it is imported or built
    check_recorded(architecture, f"{path}: architecture", {"backbone": BACKBONE, "pooling": POOLING})
    refuse_interpolations(dict(content["preprocessing"]), f"{path}: preprocessing")
    options = {"pooling": upgrade_legacy_pooling(architecture["pooling"]), "whiten_dim": architecture["whiten_dim"]}
    if model == "trainable":
        options["backbone"] = upgrade_legacy_backbone(architecture["backbone"])  # a name before 0.12
    else:
        options |= {"backbone": architecture["backbone"], "final_norm": architecture["final_norm"]}
    return get_class(CHECKPOINT_MODELS[model])(
        name=path.stem,
        weights=str(path),
        random_init=False,
        seed=0,
        max_side=max_side,
        size=size,
        scales=scales,
        extraction=CPU_EXTRACTION,
        **options,
    )


def locretrieval(
    weights: str,
    max_side: int | str | None = FROM_CHECKPOINT,
    size: tuple[int, int] | str | None = FROM_CHECKPOINT,
    scales: tuple[float, ...] | str = FROM_CHECKPOINT,
) -> DescriptorNetwork:
    """The network a locretrieval checkpoint holds (``weights``: a Lightning checkpoint of train.py,
    e.g. ``<run>/checkpoints/last.ckpt``, or a plain locretrieval checkpoint), on the CPU in eval mode:
    normalised RGB images ``float32 [B, 3, H, W]`` in, unit descriptors ``[B, D]`` out. How to
    resize and normalise images is its ``preprocessing`` (``max_side`` or ``size``, ``mean``, ``std``):
    what the network was trained at, unless ``max_side``, ``size`` or ``scales`` are given (a warning
    is logged when they differ from the trained ones)."""
    descriptor = descriptor_from_checkpoint(weights, max_side=max_side, size=size, scales=scales)
    return DescriptorNetwork(descriptor.network, descriptor.preprocessing).eval()
