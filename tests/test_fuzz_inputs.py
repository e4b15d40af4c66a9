"""The fuzz test of the files the benchmark reads (tests/fuzz_inputs.py), in its own interpreter so
that a crash of that interpreter fails this test instead of ending the test run."""

import re

import pytest
from helpers import run_python

pytest.importorskip("hypothesis", reason="hypothesis is not installed: pip install -e '.[dev]'")

#: Cases per target (kapture files, gnd pickles, cache files): about 45 s in all on 2 cores.
EXAMPLES = 2500  # per target: the fuzz test stays within a minute on the 2-core CPU


def test_mutated_input_files_end_in_a_result_or_an_error_naming_the_file():
    process = run_python(
        "import runpy, sys\n"
        f"sys.argv = ['fuzz_inputs.py', '{EXAMPLES}']\n"
        "runpy.run_path('tests/fuzz_inputs.py', run_name='__main__')\n",
        timeout=300,  # a hang fails the test too
    )
    assert process.returncode == 0, (process.stdout + process.stderr)[-6000:]  # a negative code: a crash
    summary = re.search(r"fuzz: (\d+) cases \(kapture (\d+), gnd (\d+), cache (\d+)\)", process.stdout)
    assert summary is not None and [int(n) for n in summary.groups()] == [3 * EXAMPLES] + [EXAMPLES] * 3
    print(summary.group())
