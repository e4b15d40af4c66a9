"""Files the package ships: the configs of its commands.

The repository's ``configs/`` is installed as the package ``locretrieval.configs`` (setup.py maps it:
a wheel holds ``locretrieval/configs/``, an editable install reads the repository's folder), so
that the ``locretrieval`` command and the code that composes configs find them from any folder.
"""

from __future__ import annotations

import functools
import importlib.resources
from pathlib import Path

#: The package holding the YAML configs (Hydra's search path: ``pkg://locretrieval.configs``).
CONFIGS_PACKAGE = "locretrieval.configs"


@functools.cache
def configs_dir() -> Path:
    """The folder of the shipped configs (``evaluate.yaml``, ``train.yaml``, ``export.yaml`` and the groups)."""
    try:
        return Path(str(importlib.resources.files(CONFIGS_PACKAGE)))
    except ModuleNotFoundError:  # an editable install from before configs/ was mapped into the package
        raise ModuleNotFoundError(
            f"{CONFIGS_PACKAGE} is not installed: install the package again (make venv, or pip install -e .)"
        ) from None
