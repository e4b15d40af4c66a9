"""Cross-batch memory (`memory=cross_batch`, a loss wrapper): what it remembers, the candidates it adds to a batch,
the listwise loss it gives against a direct computation, and train.py with it."""

from functools import partial

import helpers
import numpy as np
import pytest
import torch
from helpers import train
from training_runs import cheap_train_config as train_config
from training_runs import random_pairs

from locretrieval.models.networks import GeMPooling, RetrievalNet
from locretrieval.training.losses import ListwiseLoss
from locretrieval.training.memory import CrossBatchMemory, DescriptorMemory


def unit(rows: int, dim: int, seed: int) -> torch.Tensor:
    return torch.nn.functional.normalize(torch.randn(rows, dim, generator=torch.Generator().manual_seed(seed)), dim=1)


def test_the_memory_keeps_the_newest_copy_of_the_last_images_it_was_given():
    memory = DescriptorMemory(4)
    descriptors = unit(10, 3, 0)
    memory.write(descriptors[:6], torch.arange(6))
    memory.write(descriptors[6:], torch.arange(6, 10))
    assert memory.indices.tolist() == [6, 7, 8, 9]  # the last 4
    memory.write(descriptors[:2] * 0 + descriptors[7], torch.tensor([7, 7]))  # an image twice in a batch: once
    assert memory.indices.tolist() == [6, 8, 9, 7] and len(memory) == 4
    torch.testing.assert_close(memory.descriptors[-1], descriptors[7])
    trained = descriptors.clone().requires_grad_(True)
    memory.write(trained[:2], torch.tensor([0, 1]))
    assert not memory.descriptors.requires_grad  # no gradient flows into remembered images
    with pytest.raises(ValueError, match="size: must be >= 1"):
        DescriptorMemory(-1)


def test_a_batch_gains_the_remembered_images_outside_it_as_candidates_that_are_no_anchor():
    pairs = random_pairs(12, 0)
    descriptors = unit(12, 5, 1)
    memory = DescriptorMemory(100)
    memory.write(descriptors[[0, 1, 2, 3, 4, 5]], torch.tensor([0, 1, 2, 3, 4, 5]))
    batch = np.array([4, 5, 6, 7])
    relevance, negatives = (torch.from_numpy(block) for block in pairs.batch(batch))
    candidates, extended_relevance, extended_negatives = memory.extend(
        descriptors[batch], relevance, negatives, torch.from_numpy(batch), pairs
    )
    everyone = np.array([4, 5, 6, 7, 0, 1, 2, 3])  # the batch, then what it does not hold of the memory
    torch.testing.assert_close(candidates, descriptors[everyone])
    graded, related = pairs.graded.toarray(), pairs.related.toarray()
    expected_relevance = graded[everyone][:, everyone]
    expected_negatives = ~related[everyone][:, everyone] & ~np.eye(8, dtype=bool)
    expected_relevance[4:], expected_negatives[4:] = 0.0, False  # remembered images are no anchor
    np.testing.assert_allclose(extended_relevance.numpy(), expected_relevance, rtol=1e-6)
    np.testing.assert_array_equal(extended_negatives.numpy(), expected_negatives)
    empty = DescriptorMemory(3).extend(descriptors[batch], relevance, negatives, torch.from_numpy(batch), pairs)
    assert empty[0].shape == (4, 5)  # nothing remembered yet: the batch as it is


def test_the_listwise_loss_with_a_memory_ranks_each_anchor_against_every_remembered_image():
    """ListNet of each batch anchor over all its relevant and unrelated partners among the batch and
    the memory, computed here in numpy, equals the loss of the extended batch."""
    pairs = random_pairs(16, 2)
    descriptors = unit(16, 6, 3)
    memory = DescriptorMemory(16)
    memory.write(descriptors[6:], torch.arange(6, 16))
    batch = np.arange(6)
    relevance, negatives = (torch.from_numpy(block) for block in pairs.batch(batch))
    loss = ListwiseLoss(temperature=0.1, target_temperature=0.2)
    extended = memory.extend(
        descriptors[:6].clone().requires_grad_(True), relevance, negatives, torch.from_numpy(batch), pairs
    )
    value = loss(*extended)

    graded, related = pairs.graded.toarray(), pairs.related.toarray()
    similarity = descriptors.numpy().astype(np.float64) @ descriptors.numpy().T
    per_anchor = []
    for anchor in batch:
        positive = graded[anchor] > 0
        candidates = positive | (~related[anchor] & (np.arange(16) != anchor))
        if not (positive.any() and (candidates & ~positive).any()):
            continue
        target = np.exp(graded[anchor, candidates] / 0.2)
        target /= target.sum()
        logits = similarity[anchor, candidates] / 0.1
        log_predicted = logits - np.log(np.exp(logits).sum())
        per_anchor.append(-(target * log_predicted).sum())
    assert len(per_anchor) >= 3
    assert value.item() == pytest.approx(np.mean(per_anchor), rel=1e-5)
    without = loss(descriptors[:6], relevance, negatives).item()
    assert without != pytest.approx(value.item())  # the memory changed what each anchor is ranked against


def test_training_steps_fill_the_memory_and_rank_against_it():
    torch.manual_seed(0)
    network = RetrievalNet(
        torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3), torch.nn.ReLU()), GeMPooling(4, 3.0, trainable=False), 4
    )
    pairs = random_pairs(8, 4)
    calls = []

    def recording_loss(descriptors, relevance, negatives):
        calls.append((len(descriptors), descriptors.requires_grad))
        return descriptors.sum() * 0

    memory = partial(CrossBatchMemory, size=5)
    module = helpers.training_module(network, recording_loss, memory=memory, pairs=pairs)
    images = torch.randint(0, 255, (4, 3, 12, 12), dtype=torch.uint8)
    for batch in (np.array([0, 1, 2, 3]), np.array([3, 4, 5, 6])):
        relevance, negatives = (torch.from_numpy(block) for block in pairs.batch(batch))
        module.batch_loss((images, relevance, negatives, torch.from_numpy(batch)))
    assert calls == [(4, True), (4 + 3, True)]  # the second batch sees images 0, 1, 2 remembered (3 is in it)
    assert module.loss.memory.indices.tolist() == [2, 3, 4, 5, 6]  # the newest 5
    with pytest.raises(ValueError, match="module.memory needs the training pairs"):
        helpers.training_module(network, recording_loss, memory=memory)


def test_train_py_trains_with_a_memory(tmp_path):
    cfg = train_config(tmp_path, "memory=cross_batch", "module.memory.size=16", "sampler.batches_per_epoch=3")
    validator = train(cfg, tmp_path / "run")
    assert [entry["epoch"] for entry in validator.history] == [-1, 0]
    assert np.isfinite(validator.history[-1]["val/approximation/ewb/k3/5m_10deg"])


def test_a_memory_of_size_zero_is_the_loss_of_the_batch_alone():
    """``module.memory.size=0`` (the sweep's "no memory"): the wrapped loss of each batch as it is,
    nothing remembered; a negative size is refused naming the key."""
    pairs = random_pairs(12, 5)
    descriptors = unit(12, 5, 6)
    loss = ListwiseLoss(temperature=0.1, target_temperature=0.2)
    memory = CrossBatchMemory(loss, pairs, size=0)
    for batch in (np.arange(6), np.arange(6, 12)):
        relevance, negatives = (torch.from_numpy(block) for block in pairs.batch(batch))
        value = memory(descriptors[batch], relevance, negatives, torch.from_numpy(batch))
        assert value.item() == loss(descriptors[batch], relevance, negatives).item()
    assert memory.memory is None
    with pytest.raises(ValueError, match="size: must be >= 0"):
        CrossBatchMemory(loss, pairs, size=-1)
