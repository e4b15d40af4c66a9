"""The tests mirror the package (docs/development.md, "Tests"): a module's tests are
``tests/<its package path>/test_<module>.py``; what tests the whole package is in ``tests/whole/``."""

from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]
PACKAGE = TESTS.parent / "locretrieval"
#: The tests of the whole package: start-up imports, mistakes screens, docs keys, hostile and fuzzed
#: input, the configs, the scripts and benchmarks.
WHOLE = TESTS / "whole"


def module_of(test_file: Path) -> Path:
    """The module a test file names: ``tests/a/b/test_c.py`` -> ``locretrieval/a/b/c.py``."""
    relative = test_file.relative_to(TESTS)
    return PACKAGE.joinpath(*relative.parts[:-1], relative.name.removeprefix("test_"))


def is_module_or_package(path: Path) -> bool:
    return path.is_file() or (path.with_suffix("") / "__init__.py").is_file()


def test_every_test_file_names_a_module_or_package_at_its_own_path():
    files = [path for path in sorted(TESTS.rglob("test_*.py")) if WHOLE not in path.parents]
    unmatched = [str(path.relative_to(TESTS)) for path in files if not is_module_or_package(module_of(path))]
    assert len(files) > 50 and unmatched == []
    assert module_of(TESTS / "sfm" / "test_features.py") == PACKAGE / "sfm" / "features.py"
    assert not is_module_or_package(module_of(TESTS / "sfm" / "test_features_matching.py"))  # what the rule refuses
    assert is_module_or_package(module_of(TESTS / "test_groundtruth.py"))  # a package's own tests may sit beside it


def test_every_test_folder_is_a_package_mirroring_one_of_locretrieval():
    """A folder below tests/ mirrors a package of locretrieval/ (whole/ aside) and is a package itself
    (an ``__init__.py``), so that two test files of one name (tests/training/test_run.py,
    tests/export/test_run.py) stay apart under pytest's default import mode."""
    folders = [path for path in sorted(TESTS.rglob("*")) if path.is_dir() and path.name != "__pycache__"]
    assert WHOLE in folders
    assert [str(folder.relative_to(TESTS)) for folder in folders if not (folder / "__init__.py").is_file()] == []
    unmirrored = [
        str(folder.relative_to(TESTS))
        for folder in folders
        if folder != WHOLE and not (PACKAGE / folder.relative_to(TESTS) / "__init__.py").is_file()
    ]
    assert unmirrored == []
