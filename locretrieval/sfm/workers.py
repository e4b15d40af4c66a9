"""The worker processes of the SfM stages (a `locretrieval.pool.WorkerPool`)."""

from __future__ import annotations

from locretrieval.pool import WorkerPool


def _initialize_sfm_worker() -> None:
    """BLAS and torch on one thread (the processes already use every core), and no final garbage
    collection at exit (seconds over the caches' objects)."""
    import threadpoolctl
    import torch

    import locretrieval

    locretrieval.exit_without_final_collection()
    threadpoolctl.threadpool_limits(1)
    torch.set_num_threads(1)


#: The SfM workers of this process. Each imports, as it starts, what the stages' first tasks would:
#: locretrieval (zlib before pycolmap), pycolmap, torch (matching) and the stages' modules.
SFM_WORKERS = WorkerPool(
    "sfm",
    preload=("locretrieval", "pycolmap", "torch", "locretrieval.sfm.pipeline"),
    initializer=_initialize_sfm_worker,
)
