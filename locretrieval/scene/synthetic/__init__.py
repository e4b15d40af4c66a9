"""Built-in synthetic scene: a textured mall corridor or street, ray cast with torch.

``render_synthetic_dataset(settings, output_dir)`` writes ``output_dir/mapping`` (database) and
``output_dir/query`` as kapture folders with images, depth maps, dynamic-object masks and
condition tags; `RenderSettings` is the schema of its settings (``data.render``, whose defaults
are in ``configs/data/synthetic.yaml``).

The renderer (``render_synthetic_dataset``) is imported on first use (PEP 562): reading a scene
rendered earlier needs only its configuration.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from locretrieval.scene.synthetic.config import RenderSettings

if TYPE_CHECKING:
    from locretrieval.scene.synthetic.dataset import render_synthetic_dataset

__all__ = ["RenderSettings", "render_synthetic_dataset"]


def __getattr__(name: str) -> Any:
    if name != "render_synthetic_dataset":
        raise AttributeError(f"module 'locretrieval.scene.synthetic' has no attribute {name!r}")
    from locretrieval.scene.synthetic.dataset import render_synthetic_dataset

    globals()[name] = render_synthetic_dataset
    return render_synthetic_dataset


def __dir__() -> list[str]:
    return sorted([*globals(), "render_synthetic_dataset"])
