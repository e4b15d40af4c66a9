"""Hydra plugins of locretrieval (Hydra finds plugins only in the ``hydra_plugins`` package)."""
