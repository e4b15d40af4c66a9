"""Start-up cost of the entry points: what importing the benchmark loads, and the exit."""

import subprocess
import sys

#: Libraries a run that does not use them must not import (each costs from 0.3 s to 1.5 s).
HEAVY = ("torchvision", "matplotlib", "lightning", "torch._dynamo", "kornia")


def loaded_after(code: str) -> set[str]:
    script = f"import sys\n{code}\nprint(' '.join(sorted(sys.modules)))"
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    return set(result.stdout.split())


def test_the_benchmark_and_a_precomputed_model_import_no_heavy_library():
    loaded = loaded_after("import locretrieval.evaluation\nfrom locretrieval.models import PrecomputedDescriptor")
    assert {"locretrieval.evaluation", "locretrieval.models.precomputed", "torch"} <= loaded
    assert not loaded & set(HEAVY)


def test_models_are_imported_when_first_named():
    loaded = loaded_after("from locretrieval.models import DenseVLAD")
    assert "locretrieval.models.densevlad" in loaded and "kornia" in loaded
    assert not loaded & {"locretrieval.models.delg", "locretrieval.models.apgem", "torchvision"}
    assert "torchvision" in loaded_after("from locretrieval.models import DELGDescriptor")


def test_entry_points_exit_without_the_final_garbage_collection():
    code = """
import locretrieval
class Noisy:
    def __del__(self):
        print("collected")
garbage = Noisy()
garbage.cycle = garbage
del garbage
{}
print("end")
"""
    outputs = [subprocess.run([sys.executable, "-c", code.format(call)], capture_output=True, text=True, check=True).stdout.split()
               for call in ("", "locretrieval.exit_without_final_collection()")]
    assert outputs == [["end", "collected"], ["end"]]
