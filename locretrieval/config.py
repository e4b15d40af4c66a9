"""OmegaConf resolvers used by ``configs/`` (registered when ``locretrieval`` is imported)."""

from omegaconf import OmegaConf


def first_set(*values):
    """The first argument that is not null (``${first_set:${model.feature_name},precomputed}``)."""
    return next((value for value in values if value is not None), None)


if not OmegaConf.has_resolver("first_set"):
    OmegaConf.register_new_resolver("first_set", first_set)
