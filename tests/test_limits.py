"""Loaders within budgets (``limits``): no file can crash or exhaust the interpreter. The file
reproductions of #61 run as users meet them, in fresh interpreters (a crash of one cannot take the
test run with it), at once: each must end in a named error, exit status 1, within seconds (a config
naming a process is the user's own code: tests/test_parts.py)."""

import os
import pickle
import re
import resource
import struct
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from helpers import CONFIGS, set_limits

from locretrieval.cache import load_arrays, save_arrays
from locretrieval.errors import DataFileError
from locretrieval.models.files.feature_io import read_hloc_global_descriptors
from locretrieval.models.files.weights import CHECKPOINT_FORMAT, load_torch_file, read_weights
from locretrieval.models.published.netvlad import read_netvlad_struct
from locretrieval.restricted_pickle import RefusedPickleError, load_plain_pickle
from locretrieval.scene.kapture_io import KaptureFormatError, load_image_set

ROOT = CONFIGS.parent
#: A dict whose key is a tuple nested 10^6 deep: unpickling hashes the key, which overflowed the C stack.
DEEP_KEY = b"\x80\x02})" + b"\x85" * 10**6 + b"Ns."
#: The address space of the "billion laughs" run (the issue's cap).
MEMORY_CAP = 4 * 2**30
#: Seconds the three reproductions may take together on a busy 2-core machine (interpreters importing
#: torch and Hydra take most of it; the laughs checkpoint ran 87 s to a bare MemoryError before).
WITHIN = 90


def laughs(levels: int = 8, fan_out: int = 10) -> list:
    """A list of ``fan_out ** levels`` leaves in ``levels`` shared levels: a few hundred bytes pickled."""
    level: list = [0] * fan_out
    for _ in range(levels - 1):
        level = [level] * fan_out
    return level


def laughs_checkpoint(path: Path) -> Path:
    """A locretrieval checkpoint of ``model=checkpoint`` whose architecture holds 10^8 shared leaves."""
    torch.save(
        {
            "format": CHECKPOINT_FORMAT,
            "model": "trainable",
            "architecture": {"backbone": laughs(), "pooling": laughs(), "whiten_dim": None},
            "preprocessing": {"mean": [0.5] * 3, "std": [0.5] * 3},
            "state_dict": {},
            "extra": {},
        },
        path,
    )
    return path


def cap_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_CAP, MEMORY_CAP))


@pytest.mark.slow
def test_the_file_reproductions_end_in_a_named_error_within_seconds(tmp_path):
    (tmp_path / "deep.pkl").write_bytes(DEEP_KEY)
    (tmp_path / "deep.pt").write_bytes(DEEP_KEY)  # torch reads a file that is not a zip as its legacy pickles

    def evaluate(name: str, *overrides: str) -> list[str]:
        where = [f"hydra.run.dir={tmp_path / name}", f"paths.cache_dir={tmp_path / 'cache'}"]
        return [sys.executable, str(ROOT / "evaluate.py"), *overrides, *where]

    deep_key = (  # both loaders: the plain pickle's refusal printed, the torch file's raised (model=checkpoint's)
        "from locretrieval.restricted_pickle import RefusedPickleError, load_plain_pickle\n"
        "from locretrieval.models.files.weights import load_torch_file\n"
        f"try:\n    load_plain_pickle({str(tmp_path / 'deep.pkl')!r})\n"
        "except RefusedPickleError as error:\n    print(error)\n"
        f"load_torch_file({str(tmp_path / 'deep.pt')!r})\n"
    )
    commands = {
        "deep key": ([sys.executable, "-c", deep_key], None),
        "laughs": (
            evaluate("laughs", "model=checkpoint", f"model.weights={laughs_checkpoint(tmp_path / 'laughs.pt')}"),
            cap_memory,
        ),
    }
    environment = {**os.environ, "PYTHONPATH": str(ROOT)}
    started = time.monotonic()
    processes = {
        name: subprocess.Popen(
            command, cwd=ROOT, env=environment, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            preexec_fn=limit,
        )
        for name, (command, limit) in commands.items()
    }  # fmt: skip
    outputs = {name: process.communicate(timeout=300)[0] for name, process in processes.items()}
    elapsed = time.monotonic() - started
    for name, process in processes.items():
        assert process.returncode == 1, f"{name}: exit status {process.returncode}\n{outputs[name][-3000:]}"
    depth = r"refused containers nested deeper than 64 \(limits.pickle_depth\)"
    expected = {
        "deep key": [rf"deep\.pkl: {depth}", rf"deep\.pt: not a readable PyTorch file: {depth}"],
        "laughs": [r"laughs\.pt: refused a structure of more than \d+ elements and bytes counted over its shared"],
    }
    for name, patterns in expected.items():
        for pattern in patterns:
            assert re.search(pattern, outputs[name]), f"{name}: {pattern}\n{outputs[name][-3000:]}"
    assert elapsed < WITHIN, elapsed  # both at once; each was a crash or 87 s to a MemoryError


# ------------------------------------------------------------------------------ pickles


def test_a_deep_tuple_is_refused_by_the_scan_and_plain_nesting_loads(tmp_path):
    path = tmp_path / "nested.pkl"
    nested: object = 0
    for _ in range(60):
        nested = (nested,)
    path.write_bytes(pickle.dumps({nested: [nested]}, protocol=2))
    assert next(iter(load_plain_pickle(path))) == nested  # 60 levels: within limits.pickle_depth
    for _ in range(10):
        nested = (nested,)
    path.write_bytes(pickle.dumps({nested: 1}, protocol=4))
    with pytest.raises(RefusedPickleError, match=r"nested\.pkl: refused containers nested deeper than 64"):
        load_plain_pickle(path)


def test_lists_deepened_after_they_were_stored_are_bounded_by_the_walk(tmp_path):
    """Lists appended into top-down (each stored in the memo first) nest deeper than the scan sees;
    lists are never hashed, and the walk refuses them."""
    lists = 200
    stream = b"\x80\x02" + b"".join(b"]r" + struct.pack("<I", i) + b"0" for i in range(lists))  # made, stored, popped
    stream += b"".join(b"j" + struct.pack("<I", i) + b"j" + struct.pack("<I", i + 1) + b"a0" for i in range(lists - 1))
    path = tmp_path / "lists.pkl"
    path.write_bytes(stream + b"j\x00\x00\x00\x00.")  # the first list: 200 deep
    depth, value = 0, pickle.loads(path.read_bytes())
    while value:
        depth, value = depth + 1, value[0]
    assert depth == lists - 1
    with pytest.raises(RefusedPickleError, match=r"lists\.pkl: refused containers nested deeper than 64"):
        load_plain_pickle(path)


def test_shared_references_count_at_each_use(tmp_path):
    path = tmp_path / "laughs.pkl"
    path.write_bytes(pickle.dumps(laughs(levels=7), protocol=2))
    assert path.stat().st_size < 2000
    with pytest.raises(RefusedPickleError, match=r"laughs\.pkl: refused a structure of more than 1\d{6} elements"):
        load_plain_pickle(path)
    with pytest.raises(RefusedPickleError, match=r"laughs\.pt: refused a structure of more than"):
        load_torch_file(laughs_checkpoint(tmp_path / "laughs.pt"))


def test_an_architecture_is_compared_without_unfolding_it(tmp_path):
    """A checkpoint within the size budget whose architecture differs is named, its value shown a few levels deep."""
    path = tmp_path / "other.pt"
    torch.save(
        {
            "format": CHECKPOINT_FORMAT,
            "model": "gem",
            "architecture": {"backbone": laughs(levels=4), "pooling": {"p": 3.0}},
            "preprocessing": {},
            "state_dict": {},
            "extra": {},
        },
        path,
    )
    with pytest.raises(
        ValueError, match=r"other\.pt: architecture in the file differs .*backbone: file \[\[\[\.\.\.\], \[\.\.\.\], "
    ):
        read_weights(path, "gem", {"backbone": "resnet18", "pooling": {"p": 3.0}})
    torch.save({"format": CHECKPOINT_FORMAT, "model": "gem", "architecture": [1]}, path)
    with pytest.raises(DataFileError, match=r"other\.pt: a locretrieval checkpoint whose 'architecture' is \[1\]"):
        read_weights(path, "gem", {})


# ----------------------------------------------------------------- compressed and linked files


def compressed_npz(path: Path, member: str, raw: bytes) -> Path:
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr(member, raw)
    return path


def test_an_npz_member_expanding_past_its_budget_or_its_header_is_refused(tmp_path):
    zeros = np.zeros(2**23, dtype=np.float64)  # 64 MB of zeros: 64 kB deflated
    header = np.lib.format.header_data_from_array_1_0(zeros)
    npy = b"\x93NUMPY\x01\x00" + struct.pack("<H", 118) + repr(header).encode().ljust(117) + b"\n"
    bomb = compressed_npz(tmp_path / "bomb.npz", "x.npy", npy + zeros.tobytes())
    assert bomb.stat().st_size < 1 << 17
    with pytest.raises(
        DataFileError, match=r"bomb\.npz: member 'x\.npy' would expand to \d+ bytes .*compression_ratio"
    ):
        load_arrays(bomb)
    small = np.zeros(4)
    lying = np.lib.format.header_data_from_array_1_0(small) | {"shape": (10**12,)}
    head = b"\x93NUMPY\x01\x00" + struct.pack("<H", 118) + repr(lying).encode().ljust(117) + b"\n"
    compressed_npz(tmp_path / "lying.npz", "x.npy", head + small.tobytes())
    with pytest.raises(
        DataFileError, match=r"lying\.npz: member 'x\.npy' declares an array of shape \(1000000000000,\)"
    ):
        load_arrays(tmp_path / "lying.npz")
    save_arrays(tmp_path / "plain.npz", {"a": np.arange(5)})
    assert load_arrays(tmp_path / "plain.npz")["a"].tolist() == [0, 1, 2, 3, 4]


def test_an_npz_file_removed_while_it_is_checked_is_missing_not_damaged(tmp_path, monkeypatch):
    """A part removed by a concurrent merge between the check's two openings is a FileNotFoundError,
    which the pose cache's reader answers by listing the parts again, not a DataFileError."""
    from locretrieval import bounded_files

    path = tmp_path / "part.npz"
    save_arrays(path, {"keys": np.zeros((2, 16), np.uint8)})
    check_zip = bounded_files.check_zip

    def removed_after_the_first_opening(*args, **kwargs):
        members = check_zip(*args, **kwargs)
        path.unlink()
        return members

    monkeypatch.setattr(bounded_files, "check_zip", removed_after_the_first_opening)
    with pytest.raises(FileNotFoundError):
        load_arrays(path)


def test_a_mat_file_expanding_past_its_budget_or_declaring_huge_cells_is_refused(tmp_path):
    import scipy.io

    scipy.io.savemat(tmp_path / "bomb.mat", {"net": np.zeros(2**22)}, do_compression=True)  # 32 MB in 32 kB
    with pytest.raises(DataFileError, match=r"bomb\.mat: element at byte 128 would expand to more than"):
        read_netvlad_struct(tmp_path / "bomb.mat")
    cells = np.empty((1, 2), dtype=object)
    cells[0, 0], cells[0, 1] = np.ones(1), np.ones(1)
    scipy.io.savemat(tmp_path / "cells.mat", {"c": cells}, do_compression=False)
    data = bytearray((tmp_path / "cells.mat").read_bytes())
    dims = 128 + 8 + 16 + 8  # header, the matrix tag, its array flags, the dimensions' tag
    data[dims : dims + 8] = struct.pack("<ii", 1, 10**9)
    (tmp_path / "cells.mat").write_bytes(data)
    with pytest.raises(DataFileError, match=r"cells\.mat: a MATLAB cell array declares 1000000000 x 1 elements"):
        read_netvlad_struct(tmp_path / "cells.mat")


def test_hdf5_links_external_storage_and_unwritten_datasets_are_refused(tmp_path):
    secret = tmp_path / "secret.h5"
    with h5py.File(secret, "w") as file:
        file.create_dataset("a.jpg/global_descriptor", data=np.ones(4))
    (tmp_path / "secret.raw").write_bytes(np.ones(4).tobytes())
    features = tmp_path / "features.h5"
    with h5py.File(features, "w") as file:
        file["a.jpg"] = h5py.ExternalLink(str(secret), "a.jpg")
        file.create_dataset("b.jpg/global_descriptor", shape=(2**27,), dtype="f4", chunks=(2**16,), compression="gzip")
        file.create_dataset(
            "c.jpg/global_descriptor", shape=(4,), dtype="f8", external=[(str(tmp_path / "secret.raw"), 0, 32)]
        )
        file["d.jpg"] = h5py.SoftLink("/b.jpg")
        file.create_dataset("e.jpg/global_descriptor", data=np.full(4, 2.0))
    assert features.stat().st_size < 10_000
    refusals = {
        "a.jpg": r"/a\.jpg is a link \(ExternalLink to .*secret\.h5\); links are not followed",
        "b.jpg": r"dataset /b\.jpg/global_descriptor would expand to 536870912 bytes from 0 stored",
        "c.jpg": r"dataset /c\.jpg/global_descriptor keeps its data in external storage",
        "d.jpg": r"/d\.jpg is a link \(SoftLink to /b\.jpg\)",
    }
    for name, refusal in refusals.items():
        with pytest.raises(DataFileError, match=rf"features\.h5: {refusal}"):
            read_hloc_global_descriptors(features, [name])
    assert read_hloc_global_descriptors(features, ["e.jpg"]).tolist() == [[2.0] * 4]


# ----------------------------------------------------------------------------- kapture


def test_kapture_files_past_their_row_budget_and_images_outside_the_folder(tmp_path, monkeypatch, caplog):
    from kapture_folders import PINHOLE, write_kapture

    root = write_kapture(tmp_path / "query", {"phone": PINHOLE}, {(1, "phone"): "a.png", (2, "phone"): "b.png"})
    set_limits(monkeypatch, kapture_rows=1)
    with pytest.raises(KaptureFormatError, match=r"records_camera\.txt:\d+: more than 1 rows \(limits\.kapture_rows"):
        load_image_set(root)
    set_limits(monkeypatch, kapture_rows=10)
    shared = tmp_path / "shared.png"
    (root / "sensors" / "records_data" / "b.png").rename(shared)
    (root / "sensors" / "records_data" / "b.png").symlink_to(shared)
    assert load_image_set(root).names == ["a.png", "b.png"]  # allowed, said once
    assert [r.message for r in caplog.records if "outside the folder" in r.message] == [
        f"{root}: 1 of 2 images resolve outside the folder (symbolic links), e.g. b.png -> {shared}; "
        "limits.outside_images=refuse refuses such folders"
    ]
    set_limits(monkeypatch, outside_images="refuse")
    with pytest.raises(DataFileError, match=rf"b\.png: resolves to {shared}, outside the kapture folder"):
        load_image_set(root)
