"""The fuzz test of the files the benchmark reads (tests/fuzz_inputs.py), in its own interpreter so
that a crash of that interpreter fails this test instead of ending the test run, its address space
capped (an input that exhausts memory fails it too)."""

import re

import pytest
from helpers import run_python

pytest.importorskip("hypothesis", reason="hypothesis is not installed: pip install -e '.[dev]'")

#: Cases per target (kapture files, gnd pickles, cache files; the targets of #61 and #69 a share of it,
#: fuzz_inputs.TARGETS): about 35 s of CPU in all on 2 cores; every target drawn 120 times at least).
EXAMPLES = 600
#: The fuzzing interpreter's address space (torch, h5py, scipy and pycolmap loaded: about 1.2 GiB resident).
MEMORY_CAP = 6 * 2**30
#: The most memory one case may take above what was resident before it (MiB): an input refused
#: before it is read takes next to none; a 0-byte points3D.bin took 2.27 GB before a bad_alloc.
CASE_MIB = 64


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
    summary = re.search(r"fuzz: (\d+) cases \((.*)\); peak memory (\d+) MiB; largest case \(.*\): (.*)", process.stdout)
    assert summary is not None, process.stdout[-3000:]
    counts = {name: int(count) for name, count in re.findall(r"(\w+) (\d+)", summary.group(2))}
    shares = {
        "kapture": 1.0, "gnd": 1.0, "cache": 1.0, "nesting": 0.3, "compression": 0.3, "hdf5": 0.3, "yaml": 0.3,
        "colmap": 0.3, "photos": 0.2,
    }  # fmt: skip
    assert counts == {name: round(share * EXAMPLES) for name, share in shares.items()}
    assert int(summary.group(1)) == sum(counts.values()) and int(summary.group(3)) < MEMORY_CAP // 2**20
    largest = {name: float(mib) for name, mib in re.findall(r"(\w+) ([\d.]+)", summary.group(4))}
    assert largest.keys() == shares.keys() and max(largest.values()) < CASE_MIB, largest
    print(summary.group())
