"""Unpickling of published data files that admits plain data only.

Some published files are pickles (the revisited Oxford/Paris ground truth, ``gnd_*.pkl``; the
PCA objects inside dirtorch's ``.pt`` files). An unrestricted ``pickle.load`` runs whatever
callable a crafted file names, and even numpy's own functions are unsafe on crafted arguments:
a dtype whose pickled state declares an object field without the "holds objects" flag makes an
array whose bytes are read as Python object pointers (a crash of the interpreter). So:

- `scan_pickle` reads the opcode stream first (``pickletools.genops``, one pass, nothing built)
  and refuses containers nested deeper than ``limits.pickle_depth``: the unpickler hashes a dict
  key or a set member as it builds it, and hashing a tuple nested 10^6 deep overflows the C stack
  (a crash no ``try`` catches). Each object the stream makes carries its nesting depth, a new
  container one more than the deepest of what it holds, a list, dict or set whatever is added
  to it later; the unpickler's memo and marks are followed as it follows them.
- `load_plain_pickle` resolves only the globals of `SAFE_GLOBALS`, each a checked stand-in:
  builtin containers and scalars (from arguments already in the file, never a size: ``bytes(1
  << 44)`` is refused), ``_codecs.encode`` (latin-1 only, as pickles write bytes) and numpy's
  array, dtype and scalar reconstructors, which build numbers only: dtypes of kinds ``b i u f c``
  (no fields, no sub-arrays, no void or object dtype), from a type string and a byte order
  alone (numpy's ``__setstate__`` never sees the file's dtype state), and arrays whose bytes
  are exactly ``shape x itemsize``;
- the loaded structure is then walked (`plain_data`): anything but ``None``, numbers, strings,
  bytes, numeric arrays and scalars, dicts, lists, tuples, sets and frozensets is refused, as
  are structures that contain themselves or nest deeper than ``limits.pickle_depth``, and the
  total size counted over shared references (in time linear in the objects: each shared one is
  counted by its size, never walked again) is bounded by the file's (``limits.pickle_size_factor``:
  no "billion laughs").

Every refusal is a `RefusedPickleError` naming the file and what was refused, before anything
from the file is used. The same scan, stand-ins and walk serve ``torch.load(weights_only=True)``
(`TORCH_NUMPY_GLOBALS`; the walk with ``strict=False``, its size budget too).
"""

from __future__ import annotations

import io
import math
import pickle
import pickletools
import re
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from locretrieval import limits
from locretrieval.errors import FIX_DATA_FILE, DataFileError

#: Type strings of the dtypes an array may have: booleans, integers, floats, complex numbers.
PLAIN_DTYPE = re.compile(r"b1|\?|[iu][1248]|f(2|4|8|12|16)|c(8|16|24|32)")
#: Byte orders of a pickled dtype's state.
BYTE_ORDERS = ("<", ">", "|", "=")


class RefusedPickleError(DataFileError, pickle.UnpicklingError):
    """A pickle that is not plain data, or not readable: the message names the file and what was refused."""


class RefusedGlobalError(RefusedPickleError):
    """A pickle named a global outside `SAFE_GLOBALS`."""


class _Refused(pickle.UnpicklingError):
    """Raised by the stand-ins while unpickling; the loaders add the file's name."""


def _refuse(what: str) -> None:
    raise _Refused(f"refused {what}; this file may hold only plain data (numbers, strings, numeric arrays)")


def _over_budget(what: str, key: str) -> None:
    raise _Refused(f"refused {what} ({key})")


# --- numpy ---------------------------------------------------------------------------------


class PlainDtype:
    """Stand-in for ``numpy.dtype`` while unpickling: keeps the type string and the byte order
    of its pickled state, and resolves (`resolve`) to a numeric dtype built from those alone."""

    __slots__ = ("typestr", "byteorder", "dtype")

    def __new__(cls, typestr: Any = None, align: Any = False, copy: Any = True, *extra: Any) -> "PlainDtype":
        if not isinstance(typestr, str) or extra:
            _refuse(f"a dtype built from {typestr!r}")
        self = object.__new__(cls)
        self.typestr, self.byteorder, self.dtype = typestr, "=", None
        return self

    def __setstate__(self, state: Any) -> None:
        # numpy's state: (version, byte order, subarray, names, fields, elsize, alignment, flags[, metadata])
        if self.dtype is not None:
            _refuse(f"a state set on dtype {_short(self.typestr)} after its use")
        if not (isinstance(state, tuple) and len(state) >= 2 and state[1] in BYTE_ORDERS):
            _refuse(f"dtype {_short(self.typestr)} with the state {_short(state)}")
        if any(part is not None for part in state[2:5]):
            _refuse(f"dtype {_short(self.typestr)} with fields or a sub-array (state {_short(state)})")
        self.byteorder = state[1]

    def resolve(self) -> np.dtype:
        """The numeric dtype (`PLAIN_DTYPE`); refused otherwise. Later state is refused."""
        if self.dtype is None:
            if not PLAIN_DTYPE.fullmatch(self.typestr):
                _refuse(f"dtype {_short(self.typestr)} (only booleans, integers, floats and complex numbers)")
            try:
                dtype = np.dtype(self.typestr)
            except TypeError:
                _refuse(f"dtype {_short(self.typestr)}, unknown to numpy")
            self.dtype = dtype.newbyteorder(self.byteorder) if self.byteorder in "<>" else dtype
        return self.dtype


def _dtype(value: Any) -> np.dtype:
    if not isinstance(value, PlainDtype):
        _refuse(f"an array or scalar of dtype {_short(value)}")
    return value.resolve()


def _shape(value: Any) -> tuple[int, ...]:
    if not (
        isinstance(value, tuple) and len(value) <= 32 and all(type(size) is int and size >= 0 for size in value)  # noqa: E721 (bool is not a size)
    ):
        _refuse(f"an array shape {_short(value)}")
    return value


def _raw_bytes(value: Any) -> bytes:
    """Array data as pickles write it: bytes, a bytearray or buffer (protocol 5), or latin-1 text (Python 2)."""
    if isinstance(value, str):
        try:
            return value.encode("latin-1")
        except UnicodeEncodeError:
            _refuse("array data that is not latin-1 text")
    if isinstance(value, (bytes, bytearray, pickle.PickleBuffer)):
        return bytes(value)
    _refuse(f"array data of type {type(value).__name__}")


def _checked_state(data: Any, dtype: Any, shape: Any) -> tuple[bytes, np.dtype, tuple[int, ...]]:
    """``(bytes, dtype, shape)`` of an array: a numeric dtype and exactly ``prod(shape) x itemsize`` bytes."""
    dtype, shape, raw = _dtype(dtype), _shape(shape), _raw_bytes(data)
    if math.prod(shape) * dtype.itemsize != len(raw):
        _refuse(f"an array of shape {shape} and dtype {dtype} from {len(raw)} bytes")
    return raw, dtype, shape


def _numeric_array(data: Any, dtype: Any, shape: Any, fortran: bool) -> np.ndarray:
    """A new array of ``shape`` from its bytes (`_checked_state`), in C or Fortran order."""
    raw, dtype, shape = _checked_state(data, dtype, shape)
    return np.frombuffer(raw, dtype=dtype).reshape(shape, order="F" if fortran else "C").copy(order="K")


class PlainArray(np.ndarray):
    """Stand-in for ``numpy.ndarray`` while unpickling: made empty by `reconstruct`, its state
    checked (`_numeric_array`) before numpy's ``__setstate__`` sees it; never called directly.
    `plain_data` turns it into a plain ``ndarray``."""

    def __new__(cls, *args: Any, **kwargs: Any) -> "PlainArray":
        _refuse("a call of numpy.ndarray (arrays are rebuilt from their pickled state only)")

    def __setstate__(self, state: Any) -> None:
        # numpy's state: ([version,] shape, dtype, is_fortran, data)
        if not (isinstance(state, tuple) and len(state) in (4, 5)):
            _refuse(f"an array with the state {_short(state)}")
        shape, dtype, fortran, data = state[-4:]
        raw, dtype, shape = _checked_state(data, dtype, shape)
        super().__setstate__((1, shape, dtype, bool(fortran), raw))


def reconstruct(subtype: Any, shape: Any = (0,), typecode: Any = b"b") -> PlainArray:
    """Stand-in for numpy's ``_reconstruct``: an empty `PlainArray` whose state comes next."""
    if subtype is not PlainArray:
        _refuse(f"numpy's _reconstruct of {_short(subtype)}")
    return np.ndarray.__new__(PlainArray, (0,), np.uint8)


def scalar(dtype: Any, data: Any = None) -> np.generic:
    """Stand-in for numpy's ``scalar``: a numeric scalar from exactly ``itemsize`` bytes."""
    return _numeric_array(data, dtype, (), False)[()]


def frombuffer(buffer: Any, dtype: Any, shape: Any, order: Any) -> np.ndarray:
    """Stand-in for numpy's ``_frombuffer`` (protocol 5)."""
    if order not in ("C", "F"):
        _refuse(f"an array order {_short(order)}")
    return _numeric_array(buffer, dtype, shape, order == "F")


# --- builtins ----------------------------------------------------------------------------


#: Arguments the builtin stand-ins accept: values already in the file, never a size or an iterator.
_MATERIAL = (str, bytes, bytearray, int, float, complex, bool, type(None), list, tuple, dict, set, frozenset)


def _checked_builtin(kind: type, accepted: tuple[type, ...], most: int) -> Callable[..., Any]:
    """``kind`` called on at most ``most`` arguments of the ``accepted`` types only (e.g. ``bytes``
    of text, never of a count)."""

    def build(*args: Any) -> Any:
        if len(args) > most or not all(isinstance(arg, accepted) and not isinstance(arg, bool) for arg in args):
            _refuse(f"the call {kind.__name__}{_short(args)}")
        return kind(*args)

    build.__name__ = kind.__name__
    return build


def encode(text: Any, encoding: Any = "utf-8") -> bytes:
    """Stand-in for ``_codecs.encode``: latin-1 text to bytes, as pickles of protocols 0-2 write bytes."""
    if not (isinstance(text, str) and encoding in ("latin1", "latin-1")):
        _refuse(f"_codecs.encode{_short((text, encoding))} (latin-1 text only)")
    return text.encode("latin-1")


_CONTAINERS = (list, tuple, dict, set, frozenset, str, bytes)
_NUMBERS = (int, float, str, bytes)
_BUILTINS: dict[str, Callable[..., Any]] = {
    **{kind.__name__: _checked_builtin(kind, _CONTAINERS, 1) for kind in (dict, list, tuple, set, frozenset)},
    **{kind.__name__: _checked_builtin(kind, _NUMBERS, 2) for kind in (int, float, complex, bool)},
    "str": _checked_builtin(str, (str, bytes), 3),
    "bytes": _checked_builtin(bytes, (str, bytes, bytearray, list), 3),
    "bytearray": _checked_builtin(bytearray, (str, bytes, bytearray, list), 3),
}

#: (module, name) -> the checked stand-in of every global a plain-data pickle may name. numpy 1.x
#: pickles arrays through ``numpy.core``, numpy 2.x through ``numpy._core`` (``_reconstruct`` up
#: to protocol 4, ``_frombuffer`` from protocol 5); protocols 0-2 write bytes as
#: ``_codecs.encode(text, 'latin1')``; Python 2 pickles name ``__builtin__`` (``long``, ``unicode``).
SAFE_GLOBALS: dict[tuple[str, str], Any] = {
    **{("builtins", name): build for name, build in _BUILTINS.items()},
    **{("__builtin__", name): build for name, build in _BUILTINS.items()},
    ("__builtin__", "long"): _BUILTINS["int"],
    ("__builtin__", "unicode"): _BUILTINS["str"],
    **{(module, "_reconstruct"): reconstruct for module in ("numpy.core.multiarray", "numpy._core.multiarray")},
    **{(module, "scalar"): scalar for module in ("numpy.core.multiarray", "numpy._core.multiarray")},
    **{(module, "_frombuffer"): frombuffer for module in ("numpy.core.numeric", "numpy._core.numeric")},
    ("numpy", "ndarray"): PlainArray,
    ("numpy", "dtype"): PlainDtype,
    ("_codecs", "encode"): encode,
}
#: ``torch.serialization.safe_globals`` entries putting the numpy stand-ins in place of numpy's own
#: (torch's restricted unpickler calls whatever is allowlisted, numpy's ``__setstate__`` included).
TORCH_NUMPY_GLOBALS = [
    (stand_in, f"{module}.{name}") for (module, name), stand_in in SAFE_GLOBALS.items() if module.startswith("numpy")
]


class _PlainDataUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in SAFE_GLOBALS:
            raise _Refused(
                f"refused to unpickle the global {module}.{name}; this file may hold only plain "
                "data (builtin containers and scalars, numpy arrays and dtypes), as the published files do"
            )
        return SAFE_GLOBALS[module, name]

    def persistent_load(self, pid: Any) -> Any:
        raise _Refused(f"refused a persistent reference ({_short(pid)}); not a plain-data pickle")


# --- the scan ------------------------------------------------------------------------------


#: Opcodes that add what follows their container (to the last mark, or one value or pair) to it.
_ADDING = {"APPEND": 1, "SETITEM": 2, "BUILD": 1, "APPENDS": None, "SETITEMS": None, "ADDITEMS": None}
#: Opcodes that make one object of everything since the last mark.
_FROM_MARK = {"TUPLE", "LIST", "DICT", "FROZENSET", "INST", "OBJ"}
_GETS = {"GET", "BINGET", "LONG_BINGET"}
_PUTS = {"PUT", "BINPUT", "LONG_BINPUT"}


def scan_pickle(stream: io.BufferedIOBase, depth_limit: int) -> None:
    """Read one pickle of ``stream`` (up to its STOP) without building anything; raise `_Refused` when an
    object it makes would nest containers deeper than ``depth_limit`` (module docstring), and on a
    stream the unpickler could not follow either (truncated, an unknown opcode, an empty stack).

    Depths are those of objects, not of stack slots: the stack and the memo hold object numbers, and
    a value added to a list, dict or set deepens that object wherever it is referenced. A container
    deepened after it was put in another leaves the other's depth as it was: only a tuple or frozenset
    (made once, from what it holds then) can be hashed, and hashing stops at the first list, dict or
    set, whose nesting the walk (`plain_data`) bounds."""
    depths: list[int] = []  # object number -> its depth
    stack: list[int] = []
    marks: list[int] = []
    memo: dict[Any, int] = {}

    def make(depth: int) -> None:
        if depth > depth_limit:
            _over_budget(f"containers nested deeper than {depth_limit}", "limits.pickle_depth")
        depths.append(depth)
        stack.append(len(depths) - 1)

    def since_mark() -> list[int]:
        start = marks.pop()
        values = stack[start:]
        del stack[start:]
        return values

    def deepest(values: list[int]) -> int:
        return max((depths[value] for value in values), default=0)

    try:
        for opcode, argument, _ in pickletools.genops(stream):
            name = opcode.name
            if name == "STOP":
                return
            if name == "MARK":
                marks.append(len(stack))
            elif name in _GETS:
                stack.append(memo[argument])
            elif name in _PUTS:
                memo[argument] = stack[-1]
            elif name == "MEMOIZE":
                memo[len(memo)] = stack[-1]
            elif name == "DUP":
                stack.append(stack[-1])
            elif name == "POP":  # the top value, or the last mark when none follows it (as the unpickler does)
                if stack and (not marks or len(stack) > marks[-1]):
                    stack.pop()
                else:
                    marks.pop()
            elif name == "POP_MARK":
                since_mark()
            elif name in _ADDING:
                count = _ADDING[name]
                values = since_mark() if count is None else [stack.pop() for _ in range(count)]
                container = stack[-1]
                depth = max(depths[container], deepest(values) + 1)
                if depth > depth_limit:
                    _over_budget(f"containers nested deeper than {depth_limit}", "limits.pickle_depth")
                depths[container] = depth
            elif name in _FROM_MARK:
                make(deepest(since_mark()) + 1)
            elif name not in ("PROTO", "FRAME"):  # every other opcode: pops its inputs, makes objects of them
                values = [stack.pop() for _ in opcode.stack_before]
                for _ in opcode.stack_after:
                    make(deepest(values) + 1 if values else 0)
    except ValueError as error:  # genops': truncated, an unknown opcode, a malformed argument
        raise _Refused(f"not a readable pickle ({error})") from None
    except IndexError:
        raise _Refused("not a readable pickle (an opcode takes a value or mark the stack lacks)") from None
    except KeyError as error:
        raise _Refused(f"not a readable pickle (memo entry {_short(error.args[0])} was never stored)") from None
    raise _Refused("not a readable pickle (no STOP opcode)")


def load_plain_pickle(path: str | Path) -> Any:
    """Read the pickle at ``path`` admitting plain data only (module docstring).

    Raises `RefusedGlobalError` naming the file and the refused global, `RefusedPickleError`
    naming the file and what else was refused or why it is not a readable pickle."""
    path = Path(path)
    data = path.read_bytes()  # the file's size bounds every read of the unpickler
    budgets = limits.current()
    try:
        scan_pickle(io.BytesIO(data), budgets.pickle_depth)
        content = _PlainDataUnpickler(io.BytesIO(data)).load()
    except _Refused as error:
        kind = RefusedGlobalError if str(error).startswith("refused to unpickle the global") else RefusedPickleError
        raise kind(path, str(error), FIX_DATA_FILE) from None
    except Exception as error:  # any failure of a crafted or damaged stream: the file is unusable
        raise RefusedPickleError(
            path, f"not a readable pickle ({type(error).__name__}: {error})", FIX_DATA_FILE
        ) from None
    return plain_data(content, path, budget=budgets.size_budget(len(data), budgets.pickle_size_factor))


# --- the walk ------------------------------------------------------------------------------


_SCALARS = (type(None), bool, int, float, complex, str, bytes, bytearray)


def plain_data(
    content: Any,
    path: str | Path,
    budget: int | None = None,
    strict: bool = True,
    holders: Iterable[type] = (),
) -> Any:
    """``content`` with the numpy stand-ins turned into plain arrays and dtypes, every array checked
    to be numeric; containers are rebuilt (dicts and lists in place).

    Structures nested deeper than ``limits.pickle_depth`` or counting more than ``budget`` (module
    docstring) are refused. ``strict``: anything but plain data is refused, and so are structures
    that contain themselves; otherwise (weights read through torch) other objects pass unchanged
    (uncounted: tensors) and instances of ``holders`` (attribute holders such as a PCA) have their
    attributes walked. Raises `RefusedPickleError` naming ``path``."""
    walk = _Walk(strict, tuple(holders), budget, limits.current().pickle_depth)
    try:
        return walk.value(content, 0)
    except _Refused as error:
        raise RefusedPickleError(path, str(error), FIX_DATA_FILE) from None


class _Walk:
    def __init__(self, strict: bool, holders: tuple[type, ...], budget: int | None, depth: int) -> None:
        self.strict, self.holders, self.budget, self.depth = strict, holders, budget, depth
        self.done: dict[
            int, tuple[Any, Any, int]
        ] = {}  # id -> (original, kept alive: ids stay unique; converted; size)
        self.open: set[int] = set()
        self.total = 0

    def value(self, item: Any, depth: int) -> Any:
        if id(item) in self.done:
            _, converted, size = self.done[id(item)]
            self._count(size)
            return converted
        if id(item) in self.open:
            if self.strict:
                _refuse("a structure that contains itself")
            return item
        if depth > self.depth:
            _over_budget(f"containers nested deeper than {self.depth}", "limits.pickle_depth")
        self.open.add(id(item))
        before = self.total
        converted = self._convert(item, depth)
        self.open.discard(id(item))
        self.done[id(item)] = (item, converted, self.total - before)
        return converted

    def _count(self, size: int) -> None:
        self.total += size
        if self.budget is not None and self.total > self.budget:
            _over_budget(
                f"a structure of more than {self.budget} elements and bytes counted over its shared references",
                "limits.pickle_size_factor x the file's bytes + 1 MiB",
            )

    def _convert(self, item: Any, depth: int) -> Any:
        if isinstance(item, PlainDtype):
            self._count(1)
            return item.resolve()
        if isinstance(item, np.ndarray):
            if item.dtype.kind not in "biufc" or item.dtype.fields is not None:
                _refuse(f"an array of dtype {item.dtype}")
            self._count(item.nbytes + 1)
            return item.view(np.ndarray) if isinstance(item, PlainArray) else item
        if isinstance(item, np.generic):
            if item.dtype.kind not in "biufc":
                _refuse(f"a scalar of dtype {item.dtype}")
            self._count(1)
            return item
        if isinstance(item, _SCALARS):
            self._count(len(item) + 1 if isinstance(item, (str, bytes, bytearray)) else 1)
            return item
        if isinstance(item, (dict, list, tuple, set, frozenset)) and (type(item) in _PLAIN_TYPES or not self.strict):
            return self._container(item, depth)
        if not self.strict:
            if isinstance(item, self.holders):
                vars(item).update({key: self.value(value, depth + 1) for key, value in vars(item).items()})
            return item
        _refuse(f"an object of type {type(item).__module__}.{type(item).__qualname__}")

    def _container(self, item: Any, depth: int) -> Any:
        self._count(1)
        if isinstance(item, dict):
            pairs = [(self.value(key, depth + 1), self.value(value, depth + 1)) for key, value in item.items()]
            if any(isinstance(key, (np.ndarray, list, dict, set)) for key, _ in pairs):
                _refuse("a dict key that is not a number, string or tuple")
            item.clear()
            try:
                item.update(pairs)
            except TypeError:
                _refuse("a dict key that cannot be hashed")
            return item
        values = [self.value(value, depth + 1) for value in item]
        if isinstance(item, list):
            item[:] = values
            return item
        if type(item) in (tuple, set, frozenset):
            try:
                return type(item)(values)
            except TypeError:
                _refuse(f"a {type(item).__name__} of unhashable values")
        return item  # a subclass torch rebuilds (torch.Size), numbers only


_PLAIN_TYPES = (dict, list, tuple, set, frozenset)


def _short(value: Any, limit: int = 80) -> str:
    """A short description of a crafted value for messages: the ``repr`` of a number or string (cut
    to ``limit`` characters), of a tuple of those, else its type (never a deep or huge ``repr``)."""
    if isinstance(value, tuple) and len(value) <= 9 and limit >= 16:
        return "(" + ", ".join(_short(part, limit // 4) for part in value) + ("," if len(value) == 1 else "") + ")"
    if isinstance(value, (str, bytes, bytearray)):
        text = repr(value[: limit + 1])
    elif isinstance(value, (bool, float, complex, type(None))) or (isinstance(value, int) and value.bit_length() < 64):
        text = repr(value)
    else:
        text = f"<{type(value).__name__}>"
    return text if len(text) <= limit else text[: limit - 3] + "..."
