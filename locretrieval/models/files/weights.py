"""Weight files: where the authors publish them, content hashes, safe loading, our checkpoints.

Nothing is downloaded: every loader takes a local path. A missing file raises
`MissingWeightsError` naming the file expected and where its authors publish it.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import reprlib
import zipfile
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from locretrieval import limits
from locretrieval.bounded_files import check_zip
from locretrieval.cache import atomic_path, tree_signature
from locretrieval.errors import FIX_DATA_FILE, DataFileError
from locretrieval.moved import current_path
from locretrieval.restricted_pickle import TORCH_NUMPY_GLOBALS, RefusedPickleError, plain_data, scan_pickle

#: Environment variable naming the folder of the weight-hash cache (default ~/.cache/locretrieval).
HASH_CACHE_ENV = "LOCRETRIEVAL_HASH_CACHE"
#: ``format`` field of the checkpoints this package writes.
CHECKPOINT_FORMAT = "locretrieval-checkpoint-v1"
#: Where a Lightning checkpoint of ``train.py`` holds our checkpoint.
EMBEDDED_CHECKPOINT_KEY = "locretrieval"
#: The first bytes of a zip archive (torch's own test for its format of files).
ZIP_MAGIC = b"PK\x03\x04"
#: Pickles at the start of a file of torch's legacy format: magic number, protocol, system, the object, storage keys.
LEGACY_PICKLES = 5


@dataclass(frozen=True)
class WeightSource:
    """The file a model expects and where its authors publish it."""

    expected: str
    publisher: str


WEIGHT_SOURCES: dict[str, WeightSource] = {
    "netvlad": WeightSource(
        "Pitts30K_struct.mat, the struct form of vd16_pitts30k_conv5_3_vlad_preL2_intra_white.mat",
        "Relja Arandjelovic publishes the MatConvNet object file at https://www.di.ens.fr/willow/research/netvlad/ "
        "(code: https://github.com/Relja/netvlad); convert it with net_class2struct.m "
        "(https://github.com/uzh-rpg/netvlad_tf_open), or use the struct file hloc hosts at "
        "https://cvg-data.inf.ethz.ch/hloc/netvlad/Pitts30K_struct.mat",
    ),
    "apgem": WeightSource(
        "Resnet101-AP-GeM-LM18.pt",
        "NAVER LABS Europe's deep-image-retrieval (dirtorch) README lists it under pre-trained models, "
        "https://github.com/naver/deep-image-retrieval",
    ),
    "delg": WeightSource(
        "a checkpoint converted from r101delg_gldv2clean_20200914 (scripts/convert_weights.py delg), "
        "or that SavedModel folder itself when tensorflow is installed",
        "the TensorFlow model garden's DELF project publishes "
        "https://storage.googleapis.com/delf/r101delg_gldv2clean_20200914.tar.gz "
        "(https://github.com/tensorflow/models/tree/master/research/delf)",
    ),
}


def torchvision_source(backbone: str) -> WeightSource:
    """Where torchvision publishes ImageNet weights for ``backbone`` (its default weights)."""
    import torchvision  # here: importing it costs more than a second

    url = torchvision.models.get_model_weights(backbone).DEFAULT.url
    return WeightSource(
        f"{url.rsplit('/', 1)[-1]} (torchvision's ImageNet weights for {backbone})", f"torchvision: {url}"
    )


class MissingWeightsError(FileNotFoundError):
    """A weight file the configuration names is not there."""


def require_weights(path: str | os.PathLike | None, source: WeightSource, model: str) -> Path:
    """``path`` as a `Path` if it exists; otherwise a `MissingWeightsError` saying what to get where."""
    if path is not None and Path(path).exists():
        return Path(path)
    where = "no model.weights path is set" if path is None else f"weight file not found: {path}"
    raise MissingWeightsError(
        f"model {model!r}: {where}; download it and set model.weights=/path/to/file "
        "(nothing is downloaded at run time)\n"
        f"  expected: {source.expected}; where to get it: {source.publisher}"
    )


def _hash_cache_file() -> Path:
    folder = os.environ.get(HASH_CACHE_ENV) or Path.home() / ".cache" / "locretrieval"
    return Path(folder) / "weight_hashes.json"


def content_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file, or of a folder's files (relative names and contents, sorted).

    Cached on disk by resolved path, sizes and modification times (`HASH_CACHE_ENV`), so an
    unchanged multi-hundred-megabyte weight file is hashed once, not on every run.
    """
    path = Path(path).resolve()
    signature = [list(entry) for entry in tree_signature(path)]  # lists, as read back from JSON
    cache_file = _hash_cache_file()
    try:
        cache = json.loads(cache_file.read_text())
    except (OSError, ValueError):
        cache = {}
    entry = cache.get(str(path))
    if isinstance(entry, dict) and entry.get("signature") == signature:
        return entry["sha256"]
    digest = hashlib.sha256()
    for relative, _, _ in signature:
        if relative:
            digest.update(f"{relative}\n".encode())
        with open(path / relative, "rb") as stream:
            for block in iter(lambda: stream.read(1 << 20), b""):
                digest.update(block)
    cache[str(path)] = {"signature": signature, "sha256": digest.hexdigest()}
    try:
        with atomic_path(cache_file) as temporary:
            temporary.write_text(json.dumps(cache, indent=1))
    except OSError:
        pass  # a read-only home only costs re-hashing next run
    return digest.hexdigest()


def load_torch_file(path: str | os.PathLike, allowed: Iterable[Any] = ()) -> Any:
    """``torch.load`` with the restricted (``weights_only``) unpickler, after `scan_torch_file`.

    Only tensors, containers, numeric numpy arrays and scalars (rebuilt by the checked stand-ins of
    `locretrieval.restricted_pickle`, never by numpy's own functions) and the ``allowed`` globals
    (objects or ``(object, "module.Name")`` pairs, see ``torch.serialization.safe_globals``) are
    rebuilt; the loaded state is then walked (`plain_data`: the attributes of ``allowed`` classes
    too; nesting and size over shared references bounded, tensors not counted) and any array that
    is not numeric refused. Errors are `DataFileError`s naming the file."""
    allowed = list(allowed)
    holders = [entry[0] if isinstance(entry, tuple) else entry for entry in allowed]
    scan_torch_file(path)
    try:
        with torch.serialization.safe_globals([*TORCH_NUMPY_GLOBALS, *allowed]):
            content = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except pickle.UnpicklingError as error:
        parts = [part.strip() for part in str(error).split("\n\n") if part.strip()]
        reason = " ".join(parts[1:-1]) or str(error)  # torch's explanation between its boilerplate
        if any(word in reason.lower() for word in ("global", "can only build", "refused")):
            raise DataFileError(path, f"refused to unpickle an object this loader does not allow: {reason}") from None
        raise DataFileError(path, f"not a readable PyTorch file ({reason})", FIX_DATA_FILE) from None
    except Exception as error:  # any failure of a crafted or damaged file (a refused numpy state included)
        reason = f"{type(error).__name__}: {error}"
        raise DataFileError(path, f"not a readable PyTorch file ({reason})", FIX_DATA_FILE) from None
    budgets = limits.current()
    budget = budgets.size_budget(os.path.getsize(path), budgets.pickle_size_factor)
    return plain_data(content, path, budget, strict=False, holders=[h for h in holders if isinstance(h, type)])


def scan_torch_file(path: str | os.PathLike) -> None:
    """Check a torch file before ``torch.load`` reads it: a zip archive (torch's format since 1.6) within
    its expansion budgets (`check_zip`: every record) and its pickles (``*.pkl`` records), or the
    pickles at the start of a legacy file, nested within ``limits.pickle_depth`` (`scan_pickle`:
    unpickling hashes keys as it builds them, and a tuple nested 10^6 deep crashed the interpreter)."""
    depth = limits.current().pickle_depth
    with open(path, "rb") as stream:
        is_zip = stream.read(len(ZIP_MAGIC)) == ZIP_MAGIC  # as torch.load tells them apart
    try:
        if not is_zip:
            with open(path, "rb") as stream:
                for _ in range(LEGACY_PICKLES):
                    scan_pickle(stream, depth)
            return
        members = check_zip(path)
        with zipfile.ZipFile(path) as archive:
            for member in members:
                if member.filename.endswith(".pkl"):
                    with archive.open(member) as stream:
                        scan_pickle(io.BufferedReader(stream), depth)
    except pickle.UnpicklingError as error:  # the scan's refusals
        raise RefusedPickleError(path, f"not a readable PyTorch file: {error}", FIX_DATA_FILE) from None
    except (zipfile.BadZipFile, OSError, EOFError) as error:
        raise DataFileError(
            path, f"not a readable PyTorch file ({type(error).__name__}: {error})", FIX_DATA_FILE
        ) from None


def save_checkpoint(
    path: str | os.PathLike,
    model: str,
    architecture: Mapping[str, Any],
    preprocessing: Mapping[str, Any],
    state_dict: Mapping[str, torch.Tensor],
    extra: Mapping[str, Any] | None = None,
) -> None:
    """Write a plain checkpoint (loadable with ``weights_only=True``) atomically.

    ``model``: the zoo name (``netvlad``, ``apgem``, ``delg``, ``gem``, ``netvlad_head``);
    ``architecture`` and ``preprocessing``: JSON-like settings the loader checks against its
    configuration; ``extra``: model-specific tensors (e.g. AP-GeM's PCA).
    """
    payload = {
        "format": CHECKPOINT_FORMAT,
        "model": model,
        "architecture": plain(dict(architecture)),
        "preprocessing": plain(dict(preprocessing)),
        "state_dict": {key: value.detach().cpu().contiguous() for key, value in state_dict.items()},
        "extra": dict(extra or {}),
    }
    with atomic_path(path) as temporary:
        torch.save(payload, temporary)


def plain(value: Any) -> Any:
    """``value`` as plain JSON types (tuples and other sequences become lists, mappings dicts), for
    storing and comparing settings."""
    return json.loads(json.dumps(value, default=_as_json))


def _as_json(value: Any) -> Any:
    if isinstance(value, Mapping):
        return dict(value)
    if isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        return list(value)
    raise TypeError(f"{type(value).__name__} is not a setting (JSON types, mappings and sequences)")


def is_checkpoint(content: Any) -> bool:
    return isinstance(content, dict) and content.get("format") == CHECKPOINT_FORMAT


def embedded_checkpoint(content: Any) -> Any:
    """Our checkpoint inside a Lightning checkpoint written by ``train.py`` (under
    `EMBEDDED_CHECKPOINT_KEY`), or ``content`` itself."""
    if isinstance(content, dict) and is_checkpoint(content.get(EMBEDDED_CHECKPOINT_KEY)):
        return content[EMBEDDED_CHECKPOINT_KEY]
    return content


@dataclass(frozen=True)
class Weights:
    """What a weight file holds for a model: the network's ``state_dict``, the ``architecture``
    and ``preprocessing`` settings it was made with (those the authors' reader knows; ``None``
    where unknown, e.g. an ImageNet state dict), and model-specific ``extra`` tensors (e.g.
    AP-GeM's PCA). ``checkpoint``: read from a locretrieval checkpoint (not the authors' file)."""

    state_dict: Mapping[str, torch.Tensor]
    architecture: Mapping[str, Any] | None = None
    preprocessing: Mapping[str, Any] | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)
    checkpoint: bool = False


#: ``read(path, content) -> Weights``: the authors' format of a model; ``content`` is ``None`` for a
#: file `read_weights` does not unpickle (its ``authors_file`` says so), else the safely loaded file.
AuthorsReader = Callable[[Path, Any], Weights]


def read_weights(
    path: str | os.PathLike,
    model: str,
    architecture: Mapping[str, Any],
    authors: AuthorsReader | None = None,
    authors_file: Callable[[Path], bool] | None = None,
    allowed: Iterable[Any] = (),
    upgrade: Callable[[Mapping[str, Any]], Mapping[str, Any]] | None = None,
) -> Weights:
    """The weights of ``model`` in ``path``, the one loader of every model: a locretrieval
    checkpoint (plain, or inside a Lightning checkpoint of train.py), checked to hold ``model``
    with the configured ``architecture``, or the authors' own file read by ``authors``. Files
    that ``authors_file`` recognises (a MATLAB struct, a TensorFlow folder) go to ``authors``
    unopened; others are read as tensors only (``.safetensors``) or with the restricted unpickler
    (``allowed`` globals), and what is not our checkpoint goes to ``authors``, which raises when
    the content is not its format; the architecture an authors' file holds is checked too.
    ``upgrade`` turns the architecture an older checkpoint recorded into today's form."""
    path = Path(path)
    if authors is not None and authors_file is not None and authors_file(path):
        return _checked(authors(path, None), path, architecture)
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file  # a tensors-only format: nothing to unpickle

        content = load_file(path)
    else:
        content = embedded_checkpoint(load_torch_file(path, allowed))
    if is_checkpoint(content):
        check_checkpoint_layout(content, path)
        if upgrade is not None:
            try:
                content = {**content, "architecture": upgrade(content["architecture"])}
            except (KeyError, TypeError, AttributeError, ValueError) as error:
                raise DataFileError(
                    path, f"its architecture is not one a locretrieval checkpoint records ({short_repr(error)})"
                ) from None
        check_checkpoint(content, path, model, architecture)
        return Weights(
            content["state_dict"], content["architecture"], content["preprocessing"], content["extra"], checkpoint=True
        )
    if authors is None:
        raise ValueError(f"{path}: not a locretrieval checkpoint of model {model!r}")
    return _checked(authors(path, content), path, architecture)


def _checked(weights: Weights, path: Path, architecture: Mapping[str, Any]) -> Weights:
    """``weights`` of an authors' file, after checking the architecture it holds (where its reader knows it)."""
    if weights.architecture is not None:
        check_architecture(weights.architecture, path, architecture)
    return weights


#: What a checkpoint holds under each key (`save_checkpoint`).
CHECKPOINT_LAYOUT = {
    "model": str,
    "architecture": Mapping,
    "preprocessing": Mapping,
    "state_dict": Mapping,
    "extra": Mapping,
}


def check_checkpoint_layout(content: Mapping[str, Any], path: Path) -> None:
    """Raise `DataFileError` unless ``content`` holds each key of `CHECKPOINT_LAYOUT` with a value of its type."""
    for key, kind in CHECKPOINT_LAYOUT.items():
        if not isinstance(content.get(key), kind):
            raise DataFileError(
                path,
                f"a locretrieval checkpoint whose {key!r} is {short_repr(content.get(key))}, not a {kind.__name__}",
                FIX_DATA_FILE,
            )


def check_checkpoint(content: Mapping[str, Any], path: Path, model: str, architecture: Mapping[str, Any]) -> None:
    """Raise unless ``content`` is our checkpoint of ``model`` with the configured ``architecture``."""
    if content.get("model") != model:
        raise ValueError(
            f"{path}: a locretrieval checkpoint of model {short_repr(content.get('model'))}, not {model!r}"
        )
    check_architecture(content["architecture"], path, architecture)


def check_architecture(stored: Mapping[str, Any], path: Path, architecture: Mapping[str, Any]) -> None:
    """Raise unless the settings a weight file holds (``stored``) equal the configured ``architecture``;
    a class is compared by its module's path of today (`current_path`: a checkpoint written before
    0.12 names ``locretrieval.models.backbones.TorchvisionBackbone``).

    The comparison walks the configured settings (`same_settings`), never more of the file's than
    they have: a file's settings may share references ("billion laughs": 1.8 KB of checkpoint held
    10^8 leaves), which a copy or a ``repr`` would unfold."""
    if not isinstance(stored, Mapping):
        raise ValueError(f"{path}: the architecture in the file is {short_repr(stored)}, not a mapping of settings")
    configured = plain(dict(architecture))
    differing = {key: value for key, value in configured.items() if not same_settings(stored.get(key), value)}
    if differing:
        details = ", ".join(
            f"{key}: file {short_repr(stored.get(key))} vs config {value!r}" for key, value in differing.items()
        )
        raise ValueError(f"{path}: architecture in the file differs from the configuration ({details})")


def same_settings(stored: Any, configured: Any) -> bool:
    """Whether a file's setting equals a configured one (plain JSON types): as JSON would compare them
    (tuples as lists, keys as text), each ``_target_`` at its `current_path`, in time bounded by
    ``configured``'s size."""
    if isinstance(configured, dict):
        if not isinstance(stored, Mapping) or len(stored) != len(configured):
            return False
        values = {str(key): value for key, value in stored.items()}
        return values.keys() == configured.keys() and all(
            (
                isinstance(values[key], str) and current_path(values[key]) == current_path(value)
                if key == "_target_" and isinstance(value, str)
                else same_settings(values[key], value)
            )
            for key, value in configured.items()
        )
    if isinstance(configured, list):
        return (
            isinstance(stored, (list, tuple))
            and len(stored) == len(configured)
            and all(same_settings(a, b) for a, b in zip(stored, configured))
        )
    if isinstance(stored, (Mapping, list, tuple, set, frozenset)) or type(stored) is not type(configured):
        return isinstance(stored, (int, float)) and isinstance(configured, (int, float)) and stored == configured
    return stored == configured


def short_repr(value: Any, limit: int = 120) -> str:
    """A ``repr`` of a value read from a file: two levels and four elements deep, at most ``limit`` characters."""
    bounded = reprlib.Repr()
    bounded.maxlevel, bounded.maxstring, bounded.maxother = 2, limit, limit
    bounded.maxdict = bounded.maxlist = bounded.maxtuple = bounded.maxset = bounded.maxfrozenset = 4
    text = bounded.repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."
