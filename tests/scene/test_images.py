"""Image folders walked safely and images within their pixel budget (`locretrieval.scene.images`):
links that loop or lead out of the folder, ``limits.outside_images`` for photo and COLMAP folders as
for kapture ones, ``limits.image_pixels`` checked on the header before anything is decoded."""

import logging
from pathlib import Path

import pytest
from helpers import set_limits
from PIL import Image

from locretrieval.errors import DataFileError
from locretrieval.scene.images import image_files, image_size, read_image


def photo(path: Path, size: tuple[int, int] = (8, 6), colour: int = 90) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", size, (colour, 20, 30)).save(path)
    return path


def test_links_that_loop_are_not_followed_and_links_out_are_allowed_or_refused(tmp_path, monkeypatch, caplog):
    folder = tmp_path / "photos"
    for name in ("a.jpg", "seq/b.png", ".thumbs/x.jpg"):
        photo(folder / name)
    (folder / "notes.txt").write_text("not an image")
    (folder / "loop").symlink_to(".")
    (folder / "again").symlink_to(".")
    (folder / "seq" / "up").symlink_to("..")
    shared = photo(tmp_path / "shared" / "c.jpg").parent
    (folder / "linked.jpg").symlink_to(shared / "c.jpg")
    with caplog.at_level(logging.WARNING):
        assert image_files(folder) == ["a.jpg", "linked.jpg", "seq/b.png"]
    assert "3 links to folders inside it are not followed" in caplog.text and "1 files are not images" in caplog.text
    assert f"1 of 3 images resolve outside the folder (symbolic links), e.g. linked.jpg -> {shared / 'c.jpg'}" in (
        caplog.text
    )
    (folder / "more").symlink_to(shared)  # a folder outside: walked when allowed
    assert image_files(folder) == ["a.jpg", "linked.jpg", "more/c.jpg", "seq/b.png"]
    set_limits(monkeypatch, outside_images="refuse")
    with pytest.raises(
        DataFileError,
        match=rf"^{folder / 'more'}: resolves to {shared}, outside the image folder {folder} \(limits.outside_images",
    ):
        image_files(folder)
    (folder / "more").unlink()
    with pytest.raises(DataFileError, match=rf"^{folder / 'linked.jpg'}: resolves to {shared / 'c.jpg'}, outside"):
        image_files(folder)


def test_a_link_to_the_root_is_walked_within_limits_folder_entries(tmp_path, monkeypatch):
    folder = tmp_path / "photos"
    photo(folder / "a.jpg")
    for index in range(30):
        photo(tmp_path / "big" / f"{index:02d}.jpg", colour=index)
    (folder / "root").symlink_to(tmp_path / "big")  # as `root -> /`: everything below it walked, once
    set_limits(monkeypatch, folder_entries=32)
    assert len(image_files(folder)) == 31
    set_limits(monkeypatch, folder_entries=31)
    with pytest.raises(DataFileError, match=rf"^{folder}: more than 31 files and folders below it"):
        image_files(folder)


def test_images_past_limits_image_pixels_are_refused_from_their_header(tmp_path, monkeypatch):
    path = photo(tmp_path / "wide.png", size=(200, 50))
    set_limits(monkeypatch, image_pixels=10_000)
    assert image_size(path) == (200, 50) and read_image(path).shape == (50, 200, 3)
    set_limits(monkeypatch, image_pixels=9_999)
    refusal = rf"^{path}: 200 x 50 = 10000 pixels, more than 9999 \(limits.image_pixels; refused before decoding"
    with pytest.raises(DataFileError, match=refusal):
        image_size(path)
    with pytest.raises(DataFileError, match=refusal):
        read_image(path, max_side=10)
