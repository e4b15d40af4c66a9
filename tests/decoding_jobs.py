"""A spawned process's target for tests/training/test_data.py, in a module light to import: a spawned
process imports its target's module, and the test module's own imports (torch, Hydra) cost seconds."""

import numpy as np

from locretrieval.training.data import decoded_images


def decode_into(paths, size, cache, results) -> None:
    """Decode ``paths`` at ``size`` through ``cache`` in this process and put their pixel sum on ``results``."""
    results.put(np.asarray(decoded_images(paths, size, cache, workers=1)).sum())
