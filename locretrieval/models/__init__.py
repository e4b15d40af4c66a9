"""Global image descriptors.

Each name is imported from its module on first use (PEP 562), so that importing one model does
not import every backbone library (torchvision alone takes more than a second).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from omegaconf import OmegaConf

#: Public name -> module of `locretrieval.models` defining it.
_MODULES = {
    "APGeMDescriptor": "apgem",
    "BoQDescriptor": "dinov2",
    "CallableDescriptor": "external",
    "DELGDescriptor": "delg",
    "DenseVLAD": "densevlad",
    "DinoV2Descriptor": "dinov2",
    "GlobalDescriptor": "base",
    "HubDescriptor": "external",
    "MegaLocDescriptor": "dinov2",
    "MissingWeightsError": "weights",
    "NetVLADDescriptor": "netvlad",
    "NetworkDescriptor": "torch_descriptor",
    "PrecomputedDescriptor": "precomputed",
    "SALADDescriptor": "dinov2",
    "TorchGlobalDescriptor": "torch_descriptor",
    "TrainableDescriptor": "trainable",
    "export_global_features": "feature_io",
    "read_hloc_global_descriptors": "feature_io",
}

__all__ = [
    "APGeMDescriptor",
    "BoQDescriptor",
    "CallableDescriptor",
    "DELGDescriptor",
    "DenseVLAD",
    "DinoV2Descriptor",
    "GlobalDescriptor",
    "HubDescriptor",
    "MegaLocDescriptor",
    "MissingWeightsError",
    "NetVLADDescriptor",
    "NetworkDescriptor",
    "PrecomputedDescriptor",
    "SALADDescriptor",
    "TorchGlobalDescriptor",
    "TrainableDescriptor",
    "export_global_features",
    "read_hloc_global_descriptors",
]


def _package_weights(name: str) -> str:
    """The config resolver ``${package_weights:efficientnet_lite0}`` (`efficientnet.package_weights`;
    registered with the package, the model module loads when it resolves)."""
    from locretrieval.models.efficientnet import package_weights

    return package_weights(name)


if not OmegaConf.has_resolver("package_weights"):
    OmegaConf.register_new_resolver("package_weights", _package_weights)


if TYPE_CHECKING:
    from locretrieval.models.apgem import APGeMDescriptor
    from locretrieval.models.base import GlobalDescriptor
    from locretrieval.models.delg import DELGDescriptor
    from locretrieval.models.densevlad import DenseVLAD
    from locretrieval.models.dinov2 import BoQDescriptor, DinoV2Descriptor, MegaLocDescriptor, SALADDescriptor
    from locretrieval.models.external import CallableDescriptor, HubDescriptor
    from locretrieval.models.feature_io import export_global_features, read_hloc_global_descriptors
    from locretrieval.models.netvlad import NetVLADDescriptor
    from locretrieval.models.precomputed import PrecomputedDescriptor
    from locretrieval.models.torch_descriptor import NetworkDescriptor, TorchGlobalDescriptor
    from locretrieval.models.trainable import TrainableDescriptor
    from locretrieval.models.weights import MissingWeightsError


def __getattr__(name: str) -> Any:
    if name not in _MODULES:
        raise AttributeError(f"module 'locretrieval.models' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"locretrieval.models.{_MODULES[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_MODULES])
