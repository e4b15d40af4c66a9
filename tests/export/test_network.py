"""A trained network through the ``locretrieval`` torch.hub entry point (`locretrieval.export.network`)."""

import re
from pathlib import Path

import numpy as np
import pytest
import torch
from networks import descriptors, lightning_checkpoint, small_model

ROOT = Path(__file__).resolve().parents[2]


def test_torch_hub_loads_a_trained_checkpoint_from_the_repository(tmp_path):
    model = small_model("gem")
    checkpoint = lightning_checkpoint(model, tmp_path / "last.ckpt")
    network = torch.hub.load(str(ROOT), "locretrieval", weights=str(checkpoint), source="local")
    assert not network.training and network.preprocessing == model.preprocessing
    images = torch.randn(3, 3, 96, 128, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        np.testing.assert_array_equal(network(images).numpy(), descriptors(model, images))
    (tmp_path / "weights.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match=r"weights.pt: not a readable PyTorch file"):
        torch.hub.load(str(ROOT), "locretrieval", weights=str(tmp_path / "weights.pt"), source="local")
    torch.save({"state_dict": {}}, tmp_path / "state.pt")
    with pytest.raises(ValueError, match=r"state.pt: not a locretrieval checkpoint"):
        torch.hub.load(str(ROOT), "locretrieval", weights=str(tmp_path / "state.pt"), source="local")


@pytest.mark.parametrize("declared", ["whiten_dim", "clusters"])
def test_sizes_a_checkpoint_declares_are_compared_with_its_weights_before_the_network_is_allocated(tmp_path, declared):
    """A 2 KB checkpoint declaring ``whiten_dim`` 600,000 (3 GB of whitening) or 2^20 NetVLAD
    clusters (5.4 GB) had the network allocated before its weights were compared."""
    from locretrieval.errors import DataFileError
    from locretrieval.export.network import descriptor_from_checkpoint

    model = small_model("gem" if declared == "whiten_dim" else "netvlad")
    model.save_checkpoint(tmp_path / "plain.pt")
    content = torch.load(tmp_path / "plain.pt", weights_only=True)
    pooled = model.network.output_dim
    if declared == "whiten_dim":  # a whitening of 4 outputs stored, 600,000 declared
        content["architecture"]["whiten_dim"] = 600_000
        content["state_dict"] |= {"whitening.weight": torch.zeros(4, pooled), "whitening.bias": torch.zeros(4)}
        name, stored, declared_shape = "whitening.weight", (4, pooled), (600_000, pooled)
    else:  # 64 clusters stored, 2^20 declared
        content["architecture"]["pooling"]["clusters"] = 2**20
        channels = pooled // 64
        name, stored, declared_shape = "pooling.centers", (64, channels), (2**20, channels)
    torch.save(content, tmp_path / "declared.pt")
    with pytest.raises(
        DataFileError,
        match=rf"declared\.pt: does not fit the network its architecture describes: {re.escape(name)} has shape "
        rf"{re.escape(str(stored))} in the file, {re.escape(str(declared_shape))} in the network \(compared before",
    ):
        descriptor_from_checkpoint(tmp_path / "declared.pt")
