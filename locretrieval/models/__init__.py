"""Global image descriptors."""

from locretrieval.models.base import GlobalDescriptor

__all__ = ["GlobalDescriptor"]
