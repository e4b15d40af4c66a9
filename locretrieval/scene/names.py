"""Image names as they become file paths and text fields: what a kapture folder accepts
(`records_name_problem`) and what the exports write (`exported_name_problem`, `check_exported_names`,
`inside`)."""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Sequence
from pathlib import Path


def records_name_problem(name: str) -> str | None:
    """Why ``name`` cannot be a file below its kapture folder's ``records_data`` (``None``: it can):
    empty, absolute, with a ``..`` component, a backslash or a control character."""
    if not name:
        return "is empty"
    if name.startswith("/") or re.match(r"[A-Za-z]:", name):
        return "is absolute; names are relative to sensors/records_data"
    if ".." in name.split("/"):
        return "has a '..' component; names must stay inside sensors/records_data"
    if "\\" in name or any(ord(character) < 32 or ord(character) == 127 for character in name):
        return "has a backslash or a control character"
    return None


def exported_name_problem(name: str) -> str | None:
    """Why ``name`` cannot be written by the exports (``None``: it can): a `records_name_problem`,
    an empty or ``.`` path component (two names would share a file or an HDF5 group), whitespace
    (hloc's pairs files split on it), a comma (kapture's files split on it, and locretrieval's
    pairs reader tells the two formats apart by it) or a leading ``#`` (a comment line)."""
    problem = records_name_problem(name)
    if problem:
        return problem
    if any(part in ("", ".") for part in name.split("/")):
        return "has an empty or '.' path component"
    if any(character.isspace() for character in name):
        return "has whitespace, which separates the fields of hloc's pairs files"
    if "," in name:
        return "has a comma, which separates the fields of kapture's files"
    if name.startswith("#"):
        return "starts with '#', which marks a comment line in pairs files"
    return None


def check_exported_names(names: Sequence[str], what: str) -> None:
    """Raise ``ValueError`` naming the first of ``names`` (images of ``what``) that the exports
    cannot write (`exported_name_problem`), or the first name given twice."""
    for name in names:
        problem = exported_name_problem(name)
        if problem:
            raise ValueError(f"{what}: image name {name[:200]!r} {problem}; nothing was exported")
    repeated = [name for name, count in Counter(names).items() if count > 1]
    if repeated:
        raise ValueError(f"{what}: image name {repeated[0][:200]!r} appears twice")


def inside(folder: str | Path, path: str | Path) -> Path:
    """``path``, refused (``ValueError``) unless it resolves inside ``folder`` (the file of a name
    that `exported_name_problem` accepts always does, unless a link below ``folder`` leads out)."""
    if not Path(path).resolve().is_relative_to(Path(folder).resolve()):
        raise ValueError(f"{str(path)[:300]!r} leads outside {folder}; nothing was written there")
    return Path(path)
