"""locretrieval: image retrieval for visual localization (Humenberger et al., IJCV 2022)."""

# pycolmap exports its own deflate/inflate symbols: importing zlib first keeps later
# compression calls (numpy savez_compressed, PNG writers) from crashing the process.
import zlib  # noqa: F401

from locretrieval import config  # noqa: F401,E402  (registers the config resolvers)

__version__ = "0.3.0"
