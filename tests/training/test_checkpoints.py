"""Checkpoints of train.py (`locretrieval.training.checkpoints`): a resumed file checked, a checkpoint
killed while written."""

from pathlib import Path

import pytest
import torch
from helpers import train
from hydra.utils import instantiate
from training_runs import cheap_train_config as train_config

#: Two epochs planned, the run stopped after the first (its last.ckpt: epoch 0), no augmentation.
INTERRUPTED = ("~augmentation", "trainer.max_epochs=2")


@pytest.fixture(scope="module")
def interrupted_run(tmp_path_factory) -> Path:
    """The folder of a train.py run of `INTERRUPTED` stopped after its first epoch, under a root
    whose cache its resumption reads: trained once for the file, a checkpoint of this project for
    one test and the run resumed (in place, as ``ckpt_path=<run>/checkpoints/last.ckpt`` is) by the
    other, which leaves last.ckpt whole (what it asserts)."""
    root = tmp_path_factory.mktemp("interrupted")
    interrupt = "+callbacks.interrupt={_target_: helpers.StopAfterEpoch, epoch: 0}"
    train(train_config(root, *INTERRUPTED, interrupt), root / "run")
    return root / "run"


@pytest.mark.slow
def test_resuming_from_a_file_that_is_not_a_checkpoint_of_this_project_is_refused_before_any_work(
    tmp_path, interrupted_run
):
    from locretrieval.training.checkpoints import check_resume_checkpoint

    (tmp_path / "notes.txt").write_text("not a checkpoint")
    torch.save({"weights": torch.zeros(2)}, tmp_path / "other.pt")
    cases = {
        tmp_path / "absent.ckpt": r"ckpt_path: .*absent.ckpt not found",
        tmp_path / "notes.txt": r"ckpt_path: .*notes.txt is not a Lightning checkpoint of locretrieval's train.py \(",
        tmp_path / "other.pt": r"ckpt_path: .*other.pt is a PyTorch file but not a Lightning checkpoint",
    }
    for path, message in cases.items():
        cfg = train_config(tmp_path / path.stem, f"ckpt_path={path}")
        with pytest.raises((ValueError, FileNotFoundError), match=message) as error:
            train(cfg, tmp_path / path.stem / "run")
        assert "weights_only" not in str(error.value)
        assert not (tmp_path / path.stem / ".cache").exists()  # refused before the scene was rendered
    # a checkpoint of another architecture
    descriptor = instantiate(train_config(tmp_path).model)
    checkpoint = interrupted_run / "checkpoints" / "last.ckpt"  # train.py's, the same model
    check_resume_checkpoint(checkpoint, descriptor.model, descriptor.architecture)
    with pytest.raises(
        ValueError, match=r"ckpt_path: .*last.ckpt.*resume with the model settings of the run that wrote it"
    ):
        check_resume_checkpoint(checkpoint, descriptor.model, {**descriptor.architecture, "whiten_dim": 64})


class Killed(Exception):
    """Stands for the kill of a process in the middle of a write."""


@pytest.mark.slow
def test_a_run_killed_while_writing_last_ckpt_keeps_the_previous_checkpoint_whole(interrupted_run, monkeypatch):
    import errno
    import os
    import shutil

    from locretrieval.training.checkpoints import check_resume_checkpoint

    root = interrupted_run.parent  # the run's own root: its cache
    last = interrupted_run / "checkpoints" / "last.ckpt"
    before = last.read_bytes()
    assert torch.load(last, weights_only=False)["epoch"] == 0

    # The next write of last.ckpt dies half-way through putting its bytes in place, as a kill would while
    # a temporary file in /tmp (another file system, e.g. tmpfs) is copied over it.
    rename = os.rename

    def across_file_systems(source, destination, *args, **kwargs):
        if str(destination).endswith("last.ckpt"):
            raise OSError(errno.EXDEV, "Invalid cross-device link")
        return rename(source, destination, *args, **kwargs)

    def killed_half_way(source, destination, *args, **kwargs):  # shutil.move's copy when rename fails
        data = Path(source).read_bytes()
        Path(destination).write_bytes(data[: len(data) // 2])
        raise Killed

    monkeypatch.setattr(os, "rename", across_file_systems)
    monkeypatch.setattr(shutil, "copyfile", killed_half_way)
    original_save = torch.save

    def save_killed_half_way(content, target, *args, **kwargs):  # our writer: dies half-way through its temporary file
        if (
            isinstance(content, dict)
            and "epoch" in content
            and str(target).endswith(".ckpt")
            and ".last.ckpt." in str(target)
        ):
            original_save(content, target, *args, **kwargs)
            Path(target).write_bytes(Path(target).read_bytes()[:1000])
            raise Killed
        return original_save(content, target, *args, **kwargs)

    monkeypatch.setattr(torch, "save", save_killed_half_way)
    with pytest.raises(Killed):
        train(train_config(root, *INTERRUPTED, f"ckpt_path={last}"), interrupted_run)
    monkeypatch.undo()
    assert last.read_bytes() == before  # the previous checkpoint, whole: resumable
    descriptor = instantiate(train_config(root).model)
    check_resume_checkpoint(last, descriptor.model, descriptor.architecture)
    assert not [path.name for path in last.parent.iterdir() if path.name.startswith(".")]  # no temporary file left
