"""Global image descriptors.

Grouped by what they are: `published` (the descriptors of the paper's benchmark with their
authors' weights: DenseVLAD and its parts, NetVLAD, AP-GeM, DELG), `trainable` (the networks
train.py trains: `TrainableDescriptor`, its backbones and heads, DINOv2 and the heads published
on it) and `files` (weight files, descriptor feature files); what they all share is here: `base`
(the `GlobalDescriptor` interface), `networks` (`RetrievalNet`, the poolings, building and filling
a network), `extraction` (the engine), `torch_descriptor`, and `external` (networks defined
elsewhere). The module paths before this grouping keep working (`locretrieval.moved`).

Each name is imported from its module on first use (PEP 562), so that importing one model does
not import every backbone library (torchvision alone takes more than a second).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from omegaconf import OmegaConf

#: Public name -> module of `locretrieval.models` defining it.
_MODULES = {
    "APGeMDescriptor": "published.apgem",
    "BoQDescriptor": "trainable.dinov2",
    "CallableDescriptor": "external",
    "DELGDescriptor": "published.delg",
    "DenseVLAD": "published.densevlad",
    "DinoV2Descriptor": "trainable.dinov2",
    "GlobalDescriptor": "base",
    "HubDescriptor": "external",
    "MegaLocDescriptor": "trainable.dinov2",
    "MissingWeightsError": "files.weights",
    "NetVLADDescriptor": "published.netvlad",
    "NetworkDescriptor": "torch_descriptor",
    "PrecomputedDescriptor": "files.precomputed",
    "SALADDescriptor": "trainable.dinov2",
    "TorchGlobalDescriptor": "torch_descriptor",
    "TrainableDescriptor": "trainable",
    "export_global_features": "files.feature_io",
    "read_hloc_global_descriptors": "files.feature_io",
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
    from locretrieval.models.trainable.efficientnet import package_weights

    return package_weights(name)


if not OmegaConf.has_resolver("package_weights"):
    OmegaConf.register_new_resolver("package_weights", _package_weights)


if TYPE_CHECKING:
    from locretrieval.models.base import GlobalDescriptor
    from locretrieval.models.external import CallableDescriptor, HubDescriptor
    from locretrieval.models.files.feature_io import export_global_features, read_hloc_global_descriptors
    from locretrieval.models.files.precomputed import PrecomputedDescriptor
    from locretrieval.models.files.weights import MissingWeightsError
    from locretrieval.models.published.apgem import APGeMDescriptor
    from locretrieval.models.published.delg import DELGDescriptor
    from locretrieval.models.published.densevlad import DenseVLAD
    from locretrieval.models.published.netvlad import NetVLADDescriptor
    from locretrieval.models.torch_descriptor import NetworkDescriptor, TorchGlobalDescriptor
    from locretrieval.models.trainable import TrainableDescriptor
    from locretrieval.models.trainable.dinov2 import BoQDescriptor, DinoV2Descriptor, MegaLocDescriptor, SALADDescriptor


def __getattr__(name: str) -> Any:
    if name not in _MODULES:
        raise AttributeError(f"module 'locretrieval.models' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"locretrieval.models.{_MODULES[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_MODULES])
