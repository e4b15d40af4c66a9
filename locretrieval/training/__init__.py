"""Training descriptors for localization: ground-truth relevance, ranking losses, Lightning."""
