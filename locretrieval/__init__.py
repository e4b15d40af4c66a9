"""locretrieval: image retrieval for visual localization (Humenberger et al., IJCV 2022)."""

import atexit
import gc
import logging  # noqa: E402
import os

# pycolmap exports its own deflate/inflate symbols: importing zlib first keeps later
# compression calls (numpy savez_compressed, PNG writers) from crashing the process.
import zlib  # noqa: F401

# faiss's loader logs at INFO each CPU-specific library it fails to find (AVX-512, AVX2) before
# the one it loads: not about the run.
logging.getLogger("faiss.loader").setLevel(logging.WARNING)
# pycolmap's glog writes INFO lines to stderr (one per SIFT extractor it creates): warnings and above
# only, in this process and the workers it starts, unless GLOG_minloglevel is set (0: everything).
os.environ.setdefault("GLOG_minloglevel", "2")

from locretrieval import config, models, moved  # noqa: F401,E402  (register the config resolvers)

moved.install()  # the module paths before 0.12 (`locretrieval.models.netvlad`) import their modules of today

__version__ = "0.11.0"


def exit_without_final_collection() -> None:
    """Skip the garbage collection the interpreter runs over every object when it exits (about
    1.5 s once torch, pycolmap and pandas are loaded): the process ends anyway. For entry points
    and worker processes, not for a library user's process."""
    atexit.register(gc.freeze)
