"""What ``report.py`` reads of a run folder someone may have shared: only files inside it, YAML within
a budget and never resolved.

- `run_file`: a file of a run, refused when it resolves (through symbolic links) outside the run;
  `outside_roots`: which of a list of files (``images.csv``'s images) lie outside given folders.
- `load_yaml`: a run's YAML file (``config.yaml``, ``.hydra/overrides.yaml``, ``multirun.yaml``) as
  plain data, composed first and counted: at most ``limits.yaml_nodes`` nodes, an alias counted at
  the size of what it names each time it is used ("billion laughs": 245 bytes of aliases made
  ``report.py`` 3x slower per level), before anything is built. Interpolations (``${oc.env:HOME}``,
  ``${now:...}``) stay the text written: `literal` escapes them where the data meets OmegaConf,
  so no resolver runs on a shared folder's files (an environment variable would reach the report).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import yaml
from omegaconf._utils import get_yaml_loader

from locretrieval import limits
from locretrieval.errors import DataFileError
from locretrieval.folders import inside

#: What to do about a run file that cannot be used.
RERUN = "the run folder is damaged: run evaluate.py again"


def run_file(run: str | os.PathLike, relative: str | os.PathLike) -> Path:
    """``run / relative``, a `DataFileError` when it resolves outside the run folder ``run``."""
    path = Path(run) / relative
    if os.path.lexists(path) and not inside(path, run):
        raise DataFileError(
            path,
            f"resolves to {os.path.realpath(path)}, outside the run folder {run}; report.py reads only inside "
            "the runs it is given",
        )
    return path


def outside_roots(paths: Iterable[str], roots: Sequence[str | os.PathLike]) -> list[str]:
    """The ``paths`` that resolve inside none of ``roots``."""
    return [path for path in paths if not any(inside(path, root) for root in roots)]


class _CountingLoader(get_yaml_loader()):  # OmegaConf's loader: its floats, no duplicate keys, safe tags only
    """Composes a document counting its nodes (aliases once each), refusing more than ``budget``."""

    budget = 0
    composed = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        self.composed += 1
        if self.composed > self.budget:
            raise _TooLarge(f"more than {self.budget} YAML nodes")
        return super().compose_node(parent, index)


class _TooLarge(Exception):
    pass


def load_yaml(path: str | os.PathLike) -> Any:
    """The YAML file ``path`` as plain Python data, within ``limits.yaml_nodes`` (module docstring);
    ``None`` for an empty file. Errors are `DataFileError`s naming the file."""
    budget = limits.current().yaml_nodes
    try:
        with open(path, "rb") as stream:
            loader = _CountingLoader(stream)
            loader.budget = budget
            try:
                node = loader.get_single_node()
                if node is None:
                    return None
                _expanded_size(node, budget, {}, set())
                return loader.construct_document(node)
            finally:
                loader.dispose()
    except _TooLarge as error:
        raise DataFileError(path, f"{error}, aliases counted at each use (limits.yaml_nodes)", RERUN) from None
    except (yaml.YAMLError, RecursionError, UnicodeDecodeError) as error:
        problem = "nested too deep" if isinstance(error, RecursionError) else str(error).replace("\n", " ")
        raise DataFileError(path, f"not a readable YAML file ({problem})", RERUN) from None


def _expanded_size(node: yaml.Node, budget: int, sizes: dict[int, int], open_nodes: set[int]) -> int:
    """Nodes ``node`` unfolds to, each alias at the size of what it names (counted once, then remembered)."""
    if id(node) in sizes:
        return sizes[id(node)]
    if id(node) in open_nodes:
        raise _TooLarge("an alias inside what it names (a structure that contains itself)")
    open_nodes.add(id(node))
    children: list[yaml.Node] = []
    if isinstance(node, yaml.SequenceNode):
        children = node.value
    elif isinstance(node, yaml.MappingNode):
        children = [child for pair in node.value for child in pair]
    size = 1 + sum(_expanded_size(child, budget, sizes, open_nodes) for child in children)
    if size > budget:
        raise _TooLarge(f"more than {budget} YAML nodes")
    open_nodes.discard(id(node))
    sizes[id(node)] = size
    return size


def literal(value: Any) -> Any:
    """``value`` (plain data) with every ``${`` escaped, so that OmegaConf keeps interpolations as text."""
    if isinstance(value, str):
        return value.replace("${", "\\${")
    if isinstance(value, dict):
        return {key: literal(item) for key, item in value.items()}
    if isinstance(value, list):
        return [literal(item) for item in value]
    return value


def mapping_at(data: Any, *keys: str) -> dict[str, Any]:
    """The mapping at ``keys`` below ``data`` (plain data of `load_yaml`), ``{}`` where there is none."""
    for key in keys:
        data = data.get(key) if isinstance(data, dict) else None
    return data if isinstance(data, dict) else {}
