"""Unpickling of published data files that admits plain data only.

Some published files are pickles (the revisited Oxford/Paris ground truth, ``gnd_*.pkl``). An
unrestricted ``pickle.load`` runs whatever callable a crafted file names, so these files are read
by `load_plain_pickle`: the only globals it resolves are Python's builtin containers and scalars
and the functions numpy's own arrays, dtypes and scalars pickle through; any other global is
refused, naming the file and the global, before anything is called.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

#: (module, name) of every global a plain-data pickle may name. numpy 1.x pickles arrays through
#: ``numpy.core``, numpy 2.x through ``numpy._core`` (``_reconstruct`` up to protocol 4,
#: ``_frombuffer`` from protocol 5); protocols 0-2 write bytes as ``_codecs.encode(text, 'latin1')``.
ALLOWED_GLOBALS: frozenset[tuple[str, str]] = frozenset(
    [
        ("builtins", name)
        for name in (
            "dict",
            "list",
            "tuple",
            "set",
            "frozenset",
            "int",
            "float",
            "complex",
            "bool",
            "str",
            "bytes",
            "bytearray",
            "slice",
            "range",
        )
    ]
    + [
        ("__builtin__", name)
        for name in (
            "dict",
            "list",
            "tuple",
            "set",
            "frozenset",
            "int",
            "float",
            "long",
            "complex",
            "bool",
            "str",
            "unicode",
            "bytes",
            "bytearray",
        )
    ]
    + [
        (module, name)
        for module in ("numpy.core.multiarray", "numpy._core.multiarray")
        for name in ("_reconstruct", "scalar")
    ]
    + [(module, "_frombuffer") for module in ("numpy.core.numeric", "numpy._core.numeric")]
    + [("numpy", "ndarray"), ("numpy", "dtype"), ("_codecs", "encode")]
)


class RefusedGlobalError(pickle.UnpicklingError):
    """A pickle named a global outside `ALLOWED_GLOBALS`."""


class _PlainDataUnpickler(pickle.Unpickler):
    def __init__(self, stream, label: str):
        super().__init__(stream)
        self._label = label

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in ALLOWED_GLOBALS:
            raise RefusedGlobalError(
                f"{self._label}: refused to unpickle the global {module}.{name}; this file may hold only plain "
                "data (builtin containers and scalars, numpy arrays and dtypes), as the published files do"
            )
        return super().find_class(module, name)

    def persistent_load(self, pid: Any) -> Any:
        raise RefusedGlobalError(f"{self._label}: refused a persistent reference ({pid!r}); not a plain-data pickle")


def load_plain_pickle(path: str | Path) -> Any:
    """Read the pickle at ``path`` admitting plain data only (see `ALLOWED_GLOBALS`).

    Raises `RefusedGlobalError` naming the file and the refused global, or ``ValueError`` naming
    the file when it is not a readable pickle.
    """
    path = Path(path)
    with open(path, "rb") as stream:
        try:
            return _PlainDataUnpickler(stream, str(path)).load()
        except RefusedGlobalError:
            raise
        except (pickle.UnpicklingError, EOFError, AttributeError, ValueError, TypeError, IndexError) as error:
            raise ValueError(f"{path}: not a readable pickle ({error})") from error
