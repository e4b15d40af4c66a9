"""What a ``_target_`` may name, by where its config comes from (docs/configuration.md, "What is code
and what is data").

A config the user runs (the command line and the config files it composes) is code, as a Python
script is: Hydra instantiates what it names, so its ``_target_`` may name any class or function of
any package on the path, the user's own included. `import_part` imports it and checks it is what its
key builds (a `PartGroup`'s base class), so that a mistake reads as one: ``paradigms.mine._target_:
my_package.Thing is not a part of paradigms.mine: a part there is a Paradigm``.

A config read as data is not code: the architecture a checkpoint records (what the torch.hub entry,
``export.py`` and ``model=checkpoint`` rebuild a network from). There every ``_target_`` must be a
part of its key's group before anything is imported (`check_recorded`): its dotted path in
locretrieval, in the libraries the group's builder names or in ``limits.trusted_packages`` (the
packages a user trusts their files to name), then a class defined there and of the group's base; and
no string of it may be an interpolation (``${oc.env:...}``), which would be resolved later, after the
check, and could name what the check did not see. Each builder states its group (`PartGroup`) beside
the code that builds it: a new kind of part needs no table elsewhere.
"""

from __future__ import annotations

import inspect
import re
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from locretrieval import limits
from locretrieval.errors import ConfigError

#: The package whose classes are parts of every group.
OWN_PACKAGE = "locretrieval"
#: A dotted import path (``package.module.Name``).
DOTTED_PATH = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*")
#: What an interpolation of OmegaConf's looks like in a string.
INTERPOLATION = re.compile(r"\$\{")


@dataclass(frozen=True)
class PartGroup:
    """What a config key's builder takes: a class of ``bases`` (none: any class), or with
    ``functions`` any function too (a hook the code calls); ``packages``: the libraries besides
    locretrieval whose classes a recorded config (data) may name there."""

    bases: tuple[type, ...] = ()
    packages: tuple[str, ...] = ()
    functions: bool = False


#: What a key without a base of its own takes: in a config the user runs any class or function
#: (`ANY_CALLABLE`), in a recorded config any class of the allowed packages (`ANY_CLASS`: a function
#: of locretrieval's, such as one that writes a file, is not a part).
ANY_CALLABLE = PartGroup(functions=True)
ANY_CLASS = PartGroup()


def import_part(target: Any, key: str, group: PartGroup = ANY_CALLABLE) -> Any:
    """The class (or function, where ``group`` takes one) that the ``_target_`` ``target`` of a config
    the user runs names at ``key``, imported; a `ConfigError` naming ``<key>._target_`` when it is
    not an import path, does not import or is not a part of ``group``."""
    found = _imported(target, key)
    _require_part(found, target, key, group)
    return found


def resolve_recorded(target: Any, key: str, group: PartGroup = ANY_CLASS) -> Any:
    """The class the ``_target_`` ``target`` of a recorded config (data) names at ``key``: checked to
    lie in locretrieval, ``group.packages`` or ``limits.trusted_packages`` before anything is
    imported, then to be defined there (a name imported into an allowed module, such as
    ``locretrieval.config.os.system``, is not) and a part of ``group``."""
    packages = (OWN_PACKAGE, *group.packages, *limits.current().trusted_packages)
    where = f"{key}._target_" if key else "_target_"
    _require_path(target, where)
    if not in_packages(target, packages):
        raise ConfigError(
            f"{where}: {target} is not a part: a recorded config (a file's, not the command line's) may name "
            f"classes of {list(packages)} only; trust another package's with limits.trusted_packages=[<package>] "
            "on your command line (nothing was imported)"
        )
    found = _imported(target, key)
    module = getattr(found, "__module__", None) or ""
    if not in_packages(module, packages):
        raise ConfigError(
            f"{where}: {target} is not a part of {key}: it is defined in {module or 'no module'}, "
            f"outside {list(packages)}"
        )
    _require_part(found, target, key, group)
    return found


def _require_path(target: Any, where: str) -> None:
    if not isinstance(target, str) or not DOTTED_PATH.fullmatch(target):
        raise ConfigError(f"{where}: {target!r} is not an import path (package.module.Class)")


def _imported(target: Any, key: str) -> Any:
    """What the import path ``target`` names, imported (Hydra's `get_object`)."""
    where = f"{key}._target_" if key else "_target_"
    _require_path(target, where)
    from hydra.utils import get_object

    try:
        return get_object(target)
    except Exception as error:  # Hydra wraps the import error
        raise ConfigError(f"{where}: cannot import {target!r} ({error})") from None


def _require_part(found: Any, target: str, key: str, group: PartGroup) -> None:
    problem = _not_a_part(found, group)
    if problem:
        where = f"{key}._target_" if key else "_target_"
        raise ConfigError(f"{where}: {target} is not a part of {key or 'the config'}: {problem}")


def in_packages(path: str, packages: Sequence[str]) -> bool:
    """Whether the dotted ``path`` lies in one of ``packages`` (itself, or below it)."""
    return any(path == package or path.startswith(f"{package}.") for package in packages)


def _not_a_part(found: Any, group: PartGroup) -> str | None:
    """Why ``found`` is not a part of ``group`` (``None``: it is)."""
    if inspect.isclass(found):
        if group.bases and not issubclass(found, group.bases):
            return f"a part there is a {' or '.join(base.__qualname__ for base in group.bases)}"
        return None
    if group.functions and callable(found):
        return None
    if inspect.isfunction(found):
        if group.bases:
            try:
                returned = typing.get_type_hints(found).get("return")
            except Exception:  # annotations that do not resolve
                returned = None
            if isinstance(returned, type) and issubclass(returned, group.bases):
                return None
            names = " or ".join(base.__qualname__ for base in group.bases)
            return f"a function there must be annotated to return a {names}"
        return "not a class"
    return "not a class"


def check_recorded(node: Any, where: str, groups: Mapping[str, PartGroup]) -> None:
    """Check a recorded config (plain data a file holds: a checkpoint's architecture) before anything
    of it is built: no string holds an interpolation, and every ``_target_`` below the key ``name``
    of ``groups`` is a part of that group (`resolve_recorded`; a ``_target_`` nested deeper in it, of
    any class of the allowed packages). ``where`` names the file or section in the errors."""
    refuse_interpolations(node, where)
    for name, group in groups.items():
        value = node.get(name) if isinstance(node, Mapping) else None
        for key, target, depth in _targets(value, f"{where}: {name}"):
            resolve_recorded(target, key, group if depth == 0 else ANY_CLASS)


def refuse_interpolations(node: Any, where: str) -> None:
    """A `ConfigError` naming the key of the first string of ``node`` (plain data) that holds an
    interpolation (``${...}``): recorded values are taken as written, never resolved."""
    if isinstance(node, Mapping):
        for name, value in node.items():
            refuse_interpolations(name, where)
            refuse_interpolations(value, f"{where}.{name}")
    elif isinstance(node, (list, tuple)):
        for index, value in enumerate(node):
            refuse_interpolations(value, f"{where}[{index}]")
    elif isinstance(node, str) and INTERPOLATION.search(node):
        raise ConfigError(
            f"{where}: {node[:80]!r} is an interpolation; a recorded config is data, taken as written, and may not "
            "hold one (it would be resolved after the check of what it names)"
        )


def _targets(node: Any, key: str, depth: int = 0) -> typing.Iterator[tuple[str, Any, int]]:
    """``(key, target, depth)`` of every ``_target_`` in plain data ``node`` (depth 0: ``node``'s own)."""
    if isinstance(node, Mapping):
        for name, value in node.items():
            if name == "_target_":
                yield key, value, depth
            else:
                yield from _targets(value, f"{key}.{name}", depth + 1)
    elif isinstance(node, (list, tuple)):
        for index, value in enumerate(node):
            yield from _targets(value, f"{key}[{index}]", depth + 1)
