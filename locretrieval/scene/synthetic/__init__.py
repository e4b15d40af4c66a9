"""Built-in synthetic scene: a textured mall corridor or street, ray cast with torch.

``render_synthetic_dataset(config, output_dir)`` writes ``output_dir/mapping`` (database) and
``output_dir/query`` as kapture folders with images, depth maps, dynamic-object masks and
condition tags; :data:`DEFAULT_CONFIG` lists every configuration key with its default.
"""

from locretrieval.scene.synthetic.config import DEFAULT_CONFIG, resolve_config
from locretrieval.scene.synthetic.dataset import render_synthetic_dataset

__all__ = ["DEFAULT_CONFIG", "render_synthetic_dataset", "resolve_config"]
