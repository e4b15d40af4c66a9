"""The fuzz test of the files the benchmark reads (tests/fuzz_inputs.py), in its own interpreter so
that a crash of that interpreter fails this test instead of ending the test run, its address space
capped (an input that exhausts memory fails it too)."""

import re

import pytest
from helpers import run_python

pytest.importorskip("hypothesis", reason="hypothesis is not installed: pip install -e '.[dev]'")

#: Cases per target (kapture files, gnd pickles, cache files; the targets of #61 a share of it, fuzz_inputs.TARGETS):
#: about 45 s of CPU in all on 2 cores.
EXAMPLES = 1500
#: The fuzzing interpreter's address space (torch, h5py and scipy loaded: about 0.9 GiB resident).
MEMORY_CAP = 4 * 2**30


@pytest.mark.slow
def test_mutated_and_crafted_input_files_end_in_a_result_or_an_error_naming_the_file():
    process = run_python(
        "import resource, runpy, sys\n"
        f"resource.setrlimit(resource.RLIMIT_AS, ({MEMORY_CAP}, {MEMORY_CAP}))\n"
        f"sys.argv = ['fuzz_inputs.py', '{EXAMPLES}']\n"
        "runpy.run_path('tests/fuzz_inputs.py', run_name='__main__')\n",
        timeout=600,  # a hang fails the test too
    )
    assert process.returncode == 0, (process.stdout + process.stderr)[-6000:]  # a negative code: a crash
    summary = re.search(r"fuzz: (\d+) cases \((.*)\); peak memory (\d+) MiB", process.stdout)
    assert summary is not None, process.stdout[-3000:]
    counts = {name: int(count) for name, count in re.findall(r"(\w+) (\d+)", summary.group(2))}
    shares = {"kapture": 1.0, "gnd": 1.0, "cache": 1.0, "nesting": 0.3, "compression": 0.3, "hdf5": 0.3, "yaml": 0.3}
    assert counts == {name: round(share * EXAMPLES) for name, share in shares.items()}
    assert int(summary.group(1)) == sum(counts.values()) and int(summary.group(3)) < MEMORY_CAP // 2**20
    print(summary.group())
