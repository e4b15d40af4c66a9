"""No module of the project unpickles a data file unrestricted (the source is read, not run)."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SOURCES = sorted(
    [*ROOT.glob("locretrieval/**/*.py"), *ROOT.glob("scripts/*.py"), *ROOT.glob("benchmarks/*.py"), *ROOT.glob("*.py")]
)

#: (file, enclosing function) of the unrestricted loads of files the project wrote itself: the worker
#: pools' shared state of a call, pickled by `WorkerPool.map` into its own temporary folder.
OWN_TEMPORARY_FILES = {("locretrieval/pool.py", "_call")}

UNRESTRICTED = {
    ("pickle", "load"),
    ("pickle", "loads"),
    ("pickle", "Unpickler"),
    ("_pickle", "load"),
    ("_pickle", "loads"),
    ("dill", "load"),
    ("dill", "loads"),
    ("joblib", "load"),
    ("pd", "read_pickle"),
    ("pandas", "read_pickle"),
    ("cloudpickle", "load"),
    ("cloudpickle", "loads"),
}


def _keyword(call: ast.Call, name: str):
    return next((keyword.value for keyword in call.keywords if keyword.arg == name), None)


def _is_true(node) -> bool:
    return isinstance(node, ast.Constant) and node.value is True


def unsafe_loads(source: str) -> list[tuple[str, int, str]]:
    """(enclosing function, line, what) of each unrestricted unpickling call in ``source``."""
    found = []

    def visit(node, function: str):
        for child in ast.iter_child_nodes(node):
            scope = child.name if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)) else function
            if isinstance(child, ast.ImportFrom) and child.module in {"pickle", "_pickle", "dill", "cloudpickle"}:
                names = {alias.name for alias in child.names} & {"load", "loads", "Unpickler"}
                found.extend((function, child.lineno, f"from {child.module} import {name}") for name in names)
            if (
                isinstance(child, ast.Call)
                and isinstance(child.func, ast.Attribute)
                and isinstance(child.func.value, ast.Name)
            ):
                owner, name = child.func.value.id, child.func.attr
                if (owner, name) in UNRESTRICTED:
                    found.append((function, child.lineno, f"{owner}.{name}"))
                elif (owner, name) == ("torch", "load") and not _is_true(_keyword(child, "weights_only")):
                    found.append((function, child.lineno, "torch.load without weights_only=True"))
                elif (
                    (owner, name) in {("np", "load"), ("numpy", "load")}
                    and _keyword(child, "allow_pickle") is not None
                    and not (
                        isinstance(_keyword(child, "allow_pickle"), ast.Constant)
                        and _keyword(child, "allow_pickle").value is False
                    )
                ):
                    found.append((function, child.lineno, "np.load with allow_pickle"))
            visit(child, scope)

    visit(ast.parse(source), "<module>")
    return found


@pytest.mark.parametrize(
    "snippet, what",
    [
        ("import pickle\ndef read(f):\n    return pickle.load(open(f, 'rb'))", "pickle.load"),
        ("import pickle\ncontent = pickle.loads(b'')", "pickle.loads"),
        ("from pickle import load", "from pickle import load"),
        (
            "import torch\ndef read(f):\n    return torch.load(f, map_location='cpu')",
            "torch.load without weights_only=True",
        ),
        ("import torch\ntorch.load('x', weights_only=False)", "torch.load without weights_only=True"),
        ("import numpy as np\nnp.load('x.npy', allow_pickle=True)", "np.load with allow_pickle"),
        ("import pandas as pd\npd.read_pickle('x')", "pd.read_pickle"),
    ],
)
def test_the_scan_finds_each_kind_of_unrestricted_load(snippet, what):
    assert [entry[2] for entry in unsafe_loads(snippet)] == [what]


def test_restricted_loads_pass_the_scan():
    assert (
        unsafe_loads(
            "import torch, numpy as np\ntorch.load('x', map_location='cpu', weights_only=True)\n"
            "np.load('x.npy', allow_pickle=False)\nnp.load('y.npz')"
        )
        == []
    )


def test_no_module_unpickles_anything_but_its_own_temporary_files():
    assert len(SOURCES) > 50
    offending = []
    for path in SOURCES:
        relative = path.relative_to(ROOT).as_posix()
        for function, line, what in unsafe_loads(path.read_text()):
            if (relative, function) not in OWN_TEMPORARY_FILES:
                offending.append(f"{relative}:{line} ({function}): {what}")
    assert offending == []
    # the one allowed load is still where the allow-list says (an entry cannot outlive its call)
    workers = unsafe_loads((ROOT / "locretrieval/pool.py").read_text())
    assert {("locretrieval/pool.py", function) for function, _, _ in workers} == OWN_TEMPORARY_FILES
