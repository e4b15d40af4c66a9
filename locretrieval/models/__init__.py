"""Global image descriptors."""

from locretrieval.models.apgem import APGeMDescriptor
from locretrieval.models.base import GlobalDescriptor
from locretrieval.models.delg import DELGDescriptor
from locretrieval.models.densevlad import DenseVLAD
from locretrieval.models.feature_io import export_global_features, read_hloc_global_descriptors
from locretrieval.models.netvlad import NetVLADDescriptor
from locretrieval.models.precomputed import PrecomputedDescriptor
from locretrieval.models.torch_descriptor import NetworkDescriptor, TorchGlobalDescriptor
from locretrieval.models.trainable import TrainableDescriptor
from locretrieval.models.weights import MissingWeightsError

__all__ = [
    "APGeMDescriptor",
    "DELGDescriptor",
    "DenseVLAD",
    "GlobalDescriptor",
    "MissingWeightsError",
    "NetVLADDescriptor",
    "NetworkDescriptor",
    "PrecomputedDescriptor",
    "TorchGlobalDescriptor",
    "TrainableDescriptor",
    "export_global_features",
    "read_hloc_global_descriptors",
]
