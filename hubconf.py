"""torch.hub entry point: a network trained by locretrieval's train.py, from its checkpoint alone.

    model = torch.hub.load("<this repository's folder>", "locretrieval", weights="<run>/checkpoints/last.ckpt",
                           source="local")
    descriptors = model(images)  # normalised RGB [B, 3, H, W] -> unit [B, D]; see model.preprocessing
    # model.preprocessing: the max_side (or size), mean and std the network was trained at; max_side=...,
    # size=... or scales=... given to torch.hub.load override them (logged when they differ)

Nothing is downloaded: ``weights`` is a local file (`locretrieval.export.network.locretrieval`).
"""

dependencies = ["torch", "timm", "numpy", "PIL", "hydra", "omegaconf"]  # what building a network imports

from locretrieval.export.network import locretrieval  # noqa: E402, F401
