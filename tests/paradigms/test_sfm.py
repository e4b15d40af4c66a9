"""The SfM paradigms on the verbs of `locretrieval.sfm` (`locretrieval.paradigms.sfm`): the paradigms
drive the SfM pipeline, which knows none of them (their runs: tests/sfm/test_pipeline.py)."""

import ast
import importlib
import inspect
from pathlib import Path

import pytest
from helpers import evaluate_config

import locretrieval
from locretrieval.config import validated
from locretrieval.paradigms.base import Paradigms
from locretrieval.paradigms.sfm import SfmParadigm
from locretrieval.sfm import pipeline

PACKAGE = Path(locretrieval.__file__).parent


def package_modules(package: str) -> list[str]:
    """The dotted names of the modules of ``locretrieval.<package>``."""
    return [f"locretrieval.{package}.{path.stem}" for path in sorted((PACKAGE / package).glob("*.py"))]


@pytest.mark.parametrize("module", package_modules("paradigms"))
def test_no_paradigm_class_subclasses_a_class_of_the_sfm_package(module):
    """The pipeline calls nothing back: a paradigm says what it needs and calls the SfM verbs."""
    classes = [value for _, value in inspect.getmembers(importlib.import_module(module), inspect.isclass)]
    own = [cls for cls in classes if cls.__module__ == module]
    inherited = {
        f"{cls.__name__}({base.__module__}.{base.__name__})"
        for cls in own
        for base in cls.__mro__
        if base.__module__.startswith("locretrieval.sfm")
    }
    assert inherited == set()


def test_no_sfm_module_imports_the_paradigms():
    importing = []
    for path in sorted((PACKAGE / "sfm").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [alias.name for alias in node.names] if isinstance(node, ast.Import) else []
            names += [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            importing += [f"{path.name}: {name}" for name in names if name.startswith("locretrieval.paradigms")]
    assert importing == []
    assert not any(name.startswith("Sfm") and inspect.isabstract(value) for name, value in vars(pipeline).items())


def test_the_enabled_sfm_paradigms_are_those_of_sfm_paradigm_classes():
    paradigms = validated(Paradigms, evaluate_config("paths.root_dir=/nonexistent").paradigms, "paradigms")
    sfm = paradigms.sfm_paradigms()
    assert list(sfm) == ["local_sfm", "global_sfm"]
    assert all(isinstance(paradigm, SfmParadigm) and paradigm.uses_sfm for paradigm in sfm.values())
    assert not paradigms.approximation.uses_sfm
    assert paradigms.only(lambda paradigm: not paradigm.uses_sfm).sfm_paradigms() == {}
