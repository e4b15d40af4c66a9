"""Folders walked and written safely (`locretrieval.folders`): no link followed into a loop or twice,
none out of the folder unless asked, a budget on what is listed; a folder to write holding a link
out of it is refused naming the link."""

import os
from pathlib import Path

import pytest
from helpers import set_limits

from locretrieval.errors import DataFileError
from locretrieval.folders import check_written_folder, walk


def tree(root: Path, files: list[str]) -> Path:
    for name in files:
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(name)
    return root


def names(folder: Path, **options) -> list[str]:
    return [entry.name for entry in walk(folder, **{"hidden": False, "follow_outside": True, **options})]


def test_links_to_folders_inside_are_not_followed_and_a_folder_outside_is_walked_once(tmp_path):
    folder = tree(tmp_path / "images", ["a.jpg", "seq/b.jpg", ".hidden/c.jpg"])
    outside = tree(tmp_path / "shared", ["d.jpg", "deep/e.jpg"])
    for link, target in {"self": ".", "up": "..", "alias": "seq", "ext": outside, "ext2": outside}.items():
        (folder / link).symlink_to(target)
    (outside / "back").symlink_to(folder)  # from outside into the folder: inside, not followed
    entries = {entry.name: entry for entry in walk(folder, hidden=False, follow_outside=True)}
    assert sorted(entries) == [
        "a.jpg",
        "alias",
        "ext",
        "ext/back",
        "ext/d.jpg",
        "ext/deep",
        "ext/deep/e.jpg",
        "ext2",
        "self",
        "seq",
        "seq/b.jpg",
        "up",
        "up/images",
        "up/shared",
    ]  # fmt: skip  (up/images is the folder itself, up/shared what ext showed: listed, not walked again)
    assert entries["ext"].outside and entries["ext"].target == str(outside) and entries["ext"].is_dir
    assert entries["up"].outside and entries["up"].target == str(tmp_path)  # its folder above: the whole tree once
    assert not entries["self"].outside and entries["self"].target == str(folder)
    assert entries["seq"].target is None and not entries["seq"].outside
    assert sorted(names(folder, follow_outside=False)) == [
        "a.jpg",
        "alias",
        "ext",
        "ext2",
        "self",
        "seq",
        "seq/b.jpg",
        "up",
    ]
    assert ".hidden/c.jpg" in names(folder, hidden=True)


def test_a_walk_lists_at_most_limits_folder_entries(tmp_path, monkeypatch):
    folder = tree(tmp_path / "images", [f"{i:02d}.jpg" for i in range(12)])
    set_limits(monkeypatch, folder_entries=12)
    assert len(names(folder)) == 12
    set_limits(monkeypatch, folder_entries=11)
    with pytest.raises(
        DataFileError, match=rf"^{folder}: more than 11 files and folders below it \(limits.folder_entries"
    ):
        names(folder)


def test_a_folder_to_write_holding_a_link_out_of_it_is_refused_naming_the_link(tmp_path):
    run = tree(tmp_path / "run", ["results.csv", "rankings/a.npz"])
    check_written_folder(tmp_path / "not yet", "run folder")  # nothing there yet: nothing planted
    (run / "rankings" / "last.npz").symlink_to("a.npz")  # inside: left alone
    (run / ".hydra").mkdir()
    (run / ".hydra" / "config.yaml").symlink_to("../results.csv")
    check_written_folder(run, "run folder")
    (run / "hloc").symlink_to(tmp_path / "elsewhere")  # a link to nowhere outside: a write would create it
    with pytest.raises(
        DataFileError,
        match=rf"^{run / 'hloc'}: a symbolic link to {tmp_path / 'elsewhere'}, outside the run folder {run}; files",
    ):
        check_written_folder(run, "run folder")
    (run / "hloc").unlink()
    (run / ".hydra" / "hydra.yaml").symlink_to(os.path.relpath(tmp_path / "victim.yaml", run / ".hydra"))
    with pytest.raises(DataFileError, match=r"\.hydra/hydra\.yaml: a symbolic link to .*victim\.yaml, outside"):
        check_written_folder(run, "run folder")
