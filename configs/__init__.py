"""The configs of the ``locretrieval`` command (Hydra's YAML), installed as the package ``locretrieval.configs``."""
