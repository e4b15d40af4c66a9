"""A torch descriptor's network as ONNX (`export_onnx`), checked against torch under onnxruntime.

The graph is `DescriptorNetwork`'s: input ``images`` ``float32 [batch, 3, height, width]``, RGB
normalised as ``(rgb / 255 - mean) / std``; output ``descriptors`` ``float32 [batch, D]``, unit
L2 norm. The batch dimension is always dynamic; height and width are dynamic too unless the
input has a fixed size (``onnx.size``, else the model's ``size``, e.g. DINOv2's 322 x 322). The
file's metadata (``metadata_props``) holds the preprocessing (``mean``, ``std``, ``max_side``,
``size``, ``multiple_of``, ``scales``), the descriptor size and the check's largest difference.

The exporter is torch's TorchScript one (``torch.onnx.export(dynamo=False)``, tracing), which needs
only the ``onnx`` package. Torch marks it deprecated in favour of its ``torch.export``-based one,
which needs ``onnxscript`` and, on a 2-core CPU, took 634 s for EfficientNet-Lite0 + GeM with a
dynamic image size (18 s with a fixed one) where this one takes 1.5 s. Adaptive pooling to a grid
(MixVPR, the GeM pyramid) does not export with a dynamic image size: give ``onnx.size``.

The file is kept only when it passes the check: onnxruntime's descriptors of random images equal
torch's within ``onnx.atol`` at the example size with a batch of 2 and at another with a batch
of 3 (with a dynamic size: portrait instead of landscape). A graph that fixed what it should not
(a reshape traced at the example's batch) is refused, saying what to change.
"""

from __future__ import annotations

import copy
import importlib.util
import json
import logging
import time
import warnings
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

import locretrieval
from locretrieval.cache import atomic_path
from locretrieval.config import ConfigError, require
from locretrieval.export.network import DescriptorNetwork
from locretrieval.models.base import GlobalDescriptor
from locretrieval.models.torch_descriptor import TorchGlobalDescriptor

log = logging.getLogger(__name__)

#: The packages an export needs besides torch: the graph's writer and the check's runtime.
PACKAGES = ("onnx", "onnxruntime")
#: The example image a dynamic-size export traces, before the model's resize: 4:3 landscape.
EXAMPLE_SIZE = (640, 480)
#: Seed of the random check images.
CHECK_SEED = 0
#: What to try when a network does not export with a dynamic image size.
SIZE_HINT = "set onnx.size=[width,height] for a fixed image size"


class OnnxExportError(RuntimeError):
    """An export that failed, or whose graph disagrees with torch; no file was kept."""


@dataclass
class OnnxSettings:
    """The ``onnx`` config section: the ONNX ``opset``, a fixed input ``size`` (``[width, height]``;
    ``None``: the model's ``size`` if it has one, else any height and width), ``atol``: the largest
    difference between onnxruntime's and torch's descriptors accepted."""

    opset: int
    size: list[int] | None
    atol: float

    def __post_init__(self) -> None:
        require(14 <= self.opset <= 20, "opset", f"must be between 14 and 20 (the exporter's), got {self.opset}")
        require(
            self.size is None or (len(self.size) == 2 and min(self.size) > 0),
            "size",
            f"must be [width, height] in pixels or null, got {self.size}",
        )
        require(self.atol > 0, "atol", f"must be > 0, got {self.atol}")

    def check_packages(self) -> None:
        """Raise `ModuleNotFoundError` saying what to install when a package an export needs is missing."""
        missing = [name for name in PACKAGES if importlib.util.find_spec(name) is None]
        if missing:
            raise ModuleNotFoundError(
                f"onnx: the export needs {' and '.join(missing)}: pip install 'locretrieval[export]' "
                f"(or pip install {' '.join(missing)})"
            )


#: The models (configs/model/) that are no torch network, so none has an ONNX graph.
NOT_NETWORKS = ("densevlad", "precomputed", "pairs")


def torch_network(model: GlobalDescriptor) -> TorchGlobalDescriptor:
    """``model`` if it is computed by a torch network; a `ConfigError` (a mistake: one screen)
    naming the models that are, otherwise."""
    if not isinstance(model, TorchGlobalDescriptor):
        raise ConfigError(
            f"export=[onnx]: model {model.name!r} ({type(model).__name__}) is not a torch network, so it has no "
            f"ONNX graph; every model but {', '.join(NOT_NETWORKS)} exports to ONNX: a trained one "
            "(model=checkpoint model.weights=<run>/checkpoints/last.ckpt), a trainable one (gem, lite0_gem, timm, "
            "netvlad_head), the zoo's networks (netvlad, apgem, delg, dinov2_*) and hub or callable modules"
        )
    return model


def export_onnx(model: TorchGlobalDescriptor, path: str | Path, settings: OnnxSettings) -> Path:
    """``model``'s `DescriptorNetwork` (a copy, on the CPU) as the ONNX file ``path``, kept only when
    onnxruntime's descriptors equal torch's (see the module's docstring); returns ``path``."""
    settings.check_packages()
    network = DescriptorNetwork(copy.deepcopy(model.network).float().cpu(), model.preprocessing).eval()
    fixed = fixed_size(model, settings)
    example = model.preprocessing.target_size(*EXAMPLE_SIZE) if fixed is None else fixed
    checks = [(2, *example)]
    checks.append((3, *model.preprocessing.target_size(*reversed(EXAMPLE_SIZE))) if fixed is None else (3, *fixed))
    if len(model.preprocessing.scales) > 1:
        log.warning(
            "%s sums %d scales %s; the ONNX graph computes one (the caller sums them)",
            model.name,
            len(model.preprocessing.scales),
            list(model.preprocessing.scales),
        )
    started = time.perf_counter()
    with atomic_path(path) as temporary:
        trace(network, temporary, example, fixed is None, settings)
        exported_s = time.perf_counter() - started
        difference = check(network, temporary, checks, settings, dynamic=fixed is None)
        describe(temporary, model, network, fixed, difference)
    log.info(
        "%s: ONNX (opset %d, %s) in %.1f s, onnxruntime within %.2g of torch: %s",
        model.name,
        settings.opset,
        "dynamic batch and image size" if fixed is None else f"dynamic batch, {fixed[0]} x {fixed[1]} images",
        exported_s,
        difference,
        path,
    )
    return Path(path)


def fixed_size(model: TorchGlobalDescriptor, settings: OnnxSettings) -> tuple[int, int] | None:
    """The fixed input ``(width, height)`` (``settings.size``, else the model's ``size``, in steps of
    its ``multiple_of``), or ``None`` for a dynamic one."""
    size = settings.size if settings.size is not None else model.preprocessing.size
    if size is None:
        return None
    return replace(model.preprocessing, size=tuple(size)).target_size(*size)


def trace(
    network: DescriptorNetwork, path: Path, size: tuple[int, int], dynamic_size: bool, settings: OnnxSettings
) -> None:
    """Export ``network`` traced on a batch of 2 images of ``size`` (``(width, height)``) to ``path``."""
    width, height = size
    axes = {0: "batch", 2: "height", 3: "width"} if dynamic_size else {0: "batch"}
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*legacy TorchScript-based ONNX export.*")
            warnings.filterwarnings("ignore", message="The feature will be removed.*")
            warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)  # the check catches what they fix
            torch.onnx.export(
                network,
                (torch.zeros(2, 3, height, width),),
                str(path),
                dynamo=False,
                input_names=["images"],
                output_names=["descriptors"],
                dynamic_axes={"images": axes, "descriptors": {0: "batch"}},
                opset_version=settings.opset,
            )
    except Exception as error:  # any exporter failure: say what failed and what to try
        reason = f"{type(error).__name__}: {str(error).splitlines()[0][:300]}"
        raise OnnxExportError(
            f"onnx: the export failed ({reason})" + (f"; {SIZE_HINT}" if dynamic_size else "")
        ) from error


def check(
    network: DescriptorNetwork, path: Path, sizes: list[tuple[int, int, int]], settings: OnnxSettings, dynamic: bool
) -> float:
    """The largest difference between onnxruntime's and torch's descriptors of random images of
    ``sizes`` (``(batch, width, height)``); `OnnxExportError` when a run fails or exceeds ``atol``."""
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.log_severity_level = 4  # its errors are raised below, with what to change
    session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    generator = torch.Generator().manual_seed(CHECK_SEED)
    largest = 0.0
    for batch, width, height in sizes:
        images = torch.randn(batch, 3, height, width, generator=generator)
        shape = f"{batch} x 3 x {height} x {width}"
        try:
            got = session.run(["descriptors"], {"images": images.numpy()})[0]
        except Exception as error:  # onnxruntime's own errors: a fixed dimension, a reshape baked in
            raise OnnxExportError(
                f"onnx: the exported graph fails on a {shape} batch under onnxruntime "
                f"({str(error).splitlines()[0][:300]}); "
                + (SIZE_HINT if dynamic else "the exporter fixed the batch size (a reshape traced at the example's)")
            ) from None
        with torch.no_grad():
            expected = network(images).numpy()
        if got.shape != expected.shape:
            raise OnnxExportError(
                f"onnx: descriptors of a {shape} batch are {got.shape} under onnxruntime, {expected.shape} in torch"
            )
        difference = float(np.abs(got - expected).max())
        if not difference <= settings.atol:
            raise OnnxExportError(
                f"onnx: on a {shape} batch onnxruntime's descriptors differ from torch's by {difference:.3g} "
                f"(> onnx.atol={settings.atol}); "
                + (SIZE_HINT if dynamic else "raise onnx.atol if that is float noise")
            )
        largest = max(largest, difference)
    return largest


def describe(
    path: Path,
    model: TorchGlobalDescriptor,
    network: DescriptorNetwork,
    fixed: tuple[int, int] | None,
    difference: float,
) -> None:
    """Write the preprocessing, the descriptor size and the check's difference into the file's metadata."""
    import onnx

    graph = onnx.load(str(path))
    preprocessing = asdict(model.preprocessing)
    properties = {
        "producer": f"locretrieval {locretrieval.__version__}",
        "model": model.name,
        "input": "images: float32 [batch, 3, height, width], RGB normalised as (rgb / 255 - mean) / std",
        "output": f"descriptors: float32 [batch, {network.output_dim}], unit L2 norm",
        "input_size": "dynamic" if fixed is None else json.dumps(list(fixed)),
        **{key: json.dumps(value) for key, value in preprocessing.items()},
        "max_abs_difference_onnxruntime_torch": f"{difference:.3g}",
    }
    onnx.helper.set_model_props(graph, properties)
    onnx.save(graph, str(path))
