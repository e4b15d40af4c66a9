"""torch.hub entry point: a network trained by locretrieval's train.py, from its checkpoint alone.

    model = torch.hub.load("<this repository's folder>", "locretrieval", weights="<run>/checkpoints/last.ckpt",
                           source="local")
    descriptors = model(images)  # normalised RGB [B, 3, H, W] -> unit [B, D]; see model.preprocessing

Nothing is downloaded: ``weights`` is a local file (`locretrieval.export.network.locretrieval`).
"""

dependencies = ["torch", "timm", "numpy", "PIL", "hydra", "omegaconf"]  # what building a network imports

from locretrieval.export.network import locretrieval  # noqa: E402, F401
