"""Fuzzing of the files the benchmark reads (run by tests/test_fuzz_inputs.py in its own interpreter).

Seeded hypothesis strategies mutate, byte by byte and field by field, each kapture text file (and
an image) of a small valid folder, a revisited ground-truth pickle and a cache ``.npz``; every case must end in a
result or in the project's error naming the file (`DataFileError`, or ``FileNotFoundError`` for a
listed file that is absent), never another exception, a hang or a crash of this interpreter.
Prints how many cases were tried: ``fuzz: N cases (kapture K, gnd G, cache C)``.

    python tests/fuzz_inputs.py [EXAMPLES_PER_TARGET]
"""

import io
import logging
import pickle
import sys
import tempfile
from collections import Counter
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from locretrieval.cache import load_arrays, save_arrays
from locretrieval.errors import DataFileError
from locretrieval.metrics.revisited import PROTOCOLS, load_revisited_groundtruth
from locretrieval.scene.kapture_io import load_image_set

#: A small valid kapture folder: two cameras (one in a rig), three images, tags.
KAPTURE_FILES = {
    "sensors/sensors.txt": "# kapture format: 1.1\n# sensor_id, name, sensor_type, [sensor_params]+\n"
    "cam, phone, camera, PINHOLE, 64, 48, 50.0, 50.0, 32.0, 24.0\n"
    "cam1, phone, camera, SIMPLE_RADIAL, 64, 48, 50.0, 32.0, 24.0, 0.01\n",
    "sensors/rigs.txt": "# rig_id, sensor_id, qw, qx, qy, qz, tx, ty, tz\nrig, cam1, 1, 0, 0, 0, 0.1, 0, 0\n",
    "sensors/trajectories.txt": "# timestamp, device_id, qw, qx, qy, qz, tx, ty, tz\n"
    "1, cam, 1, 0, 0, 0, 0, 0, 0\n2, rig, 0.7071067811865476, 0, 0.7071067811865476, 0, 1, 2, 3\n",
    "sensors/records_camera.txt": "# timestamp, device_id, image_path\n"
    "1, cam, a.png\n2, cam1, sub/b.png\n3, cam, c.png\n",
    "tags.txt": "# image_name, tags\na.png, day\nsub/b.png, night rain\n",
}
IMAGES = ["a.png", "sub/b.png", "c.png"]
#: An image file as the folder holds it (its header is read: size, format).
IMAGE_FILE = "sensors/records_data/a.png"
#: Field values a careless or hostile writer puts in a CSV field.
TOKENS = [
    "", "nan", "inf", "-inf", "-1", "0", "1e400", "1e-400", "99999999999999999999", "0x10", "02", " 1 ",
    "../x.png", "/etc/hostname", "a\\b.png", "é.png", "\x00", "x" * 5000, "PINHOLE", "rig", "cam", "camera",
]  # fmt: skip

CASES: Counter = Counter()
SETTINGS = settings(
    derandomize=True, database=None, deadline=None, suppress_health_check=list(HealthCheck), print_blob=True
)


def byte_mutation() -> st.SearchStrategy:
    """``(position fraction, bytes removed, bytes inserted)``: a replaced, inserted, deleted or cut-off span."""
    return st.tuples(st.floats(0, 1), st.integers(0, 64), st.binary(max_size=32) | st.sampled_from([b"", b"\n", b","]))


def mutate_bytes(data: bytes, mutation) -> bytes:
    fraction, removed, inserted = mutation
    position = int(fraction * len(data))
    return data[:position] + inserted + data[position + removed :]


def mutate_field(text: str, line_fraction: float, field_fraction: float, value: str) -> str:
    """``text`` with one comma-separated field of one line replaced by ``value``."""
    lines = text.split("\n")
    number = int(line_fraction * (len(lines) - 1))
    fields = lines[number].split(",")
    fields[int(field_fraction * (len(fields) - 1))] = value
    lines[number] = ",".join(fields)
    return "\n".join(lines)


def png_bytes() -> bytes:
    stream = io.BytesIO()
    Image.new("RGB", (64, 48), (90, 120, 30)).save(stream, format="PNG")
    return stream.getvalue()


def kapture_folder(root: Path, files: dict[str, bytes]) -> Path:
    """``files`` (the text files and `IMAGE_FILE`) and the other images, written below ``root``."""
    image = png_bytes()
    for name, content in {**{f"sensors/records_data/{n}": image for n in IMAGES}, **files}.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(content)
    return root


def expect_named(call, path: Path, target: str):
    """``call()``'s result; a `DataFileError` or ``FileNotFoundError`` naming ``path`` counts as handled."""
    CASES[target] += 1
    try:
        return call()
    except (DataFileError, FileNotFoundError) as error:
        if str(path) not in str(error):
            raise AssertionError(f"{target}: the error does not name {path}: {error}") from error
        return None


@given(
    file=st.sampled_from(sorted([*KAPTURE_FILES, IMAGE_FILE])),
    mutation=byte_mutation(),
    field=st.tuples(st.floats(0, 1), st.floats(0, 1), st.sampled_from(TOKENS) | st.text(max_size=12)),
    by_field=st.booleans(),
)
def fuzz_kapture(file, mutation, field, by_field):
    files = {**{name: text.encode() for name, text in KAPTURE_FILES.items()}, IMAGE_FILE: png_bytes()}
    if by_field and file in KAPTURE_FILES:
        files[file] = mutate_field(KAPTURE_FILES[file], *field).encode("utf-8", "surrogatepass")
    else:
        files[file] = mutate_bytes(files[file], mutation)
    with tempfile.TemporaryDirectory() as folder:
        root = kapture_folder(Path(folder) / "query", files)
        expect_named(lambda: load_image_set(root), root, "kapture")


GROUNDTRUTH = {
    "imlist": [f"db{i}" for i in range(6)],
    "qimlist": ["q0", "q1"],
    "gnd": [
        {"easy": [0, 3], "hard": np.array([5]), "junk": [1], "bbx": [1.5, 2.0, 40.0, 30.5]},
        {"easy": np.array([], dtype=np.int64), "hard": [2], "junk": [], "bbx": np.array([0.0, 0.0, 10.0, 10.0])},
    ],
}
PLAIN_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8) | st.binary(max_size=8)
    | st.builds(np.array, st.lists(st.integers(-5, 10), max_size=4)),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=5), children, max_size=4),
    max_leaves=12,
)  # fmt: skip


def replace_value(content: dict, path: list, value) -> dict:
    """A copy of ``content`` with the value at ``path`` (keys chosen by their position) replaced."""
    if not path:
        return value
    node = dict(content) if isinstance(content, dict) else list(content) if isinstance(content, list) else None
    if not node:
        return value
    keys = list(node) if isinstance(node, dict) else list(range(len(node)))
    key = keys[path[0] % len(keys)]
    node[key] = replace_value(node[key], path[1:], value)
    return node


@given(
    protocol=st.integers(0, pickle.HIGHEST_PROTOCOL),
    mutation=byte_mutation(),
    field=st.tuples(st.lists(st.integers(0, 7), max_size=4), PLAIN_VALUES),
    by_field=st.booleans(),
)
def fuzz_groundtruth(protocol, mutation, field, by_field):
    content = replace_value(GROUNDTRUTH, *field) if by_field else GROUNDTRUTH
    data = pickle.dumps(content, protocol=protocol)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "gnd_roxford5k.pkl"
        path.write_bytes(data if by_field else mutate_bytes(data, mutation))
        groundtruth = expect_named(lambda: load_revisited_groundtruth(path), path, "gnd")
        for protocol_name in PROTOCOLS if groundtruth is not None else ():
            groundtruth.labels(protocol_name)  # what loads is usable


@given(mutation=byte_mutation(), mutations=st.integers(1, 3))
def fuzz_cache(mutation, mutations):
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "descriptors" / "0123456789abcdef.npz"
        save_arrays(path, {"descriptors": np.ones((20, 8), dtype=np.float32), "names": np.array(["a", "b"])})
        data = path.read_bytes()
        for _ in range(mutations):
            data = mutate_bytes(data, mutation)
        path.write_bytes(data)
        expect_named(lambda: load_arrays(path), path, "cache")


def main(examples: int) -> None:
    logging.disable(logging.WARNING)  # the loaders' warnings about odd but usable files
    for fuzz in (fuzz_kapture, fuzz_groundtruth, fuzz_cache):
        settings(SETTINGS, max_examples=examples)(fuzz)()
    print(f"fuzz: {sum(CASES.values())} cases ({', '.join(f'{k} {v}' for k, v in CASES.items())})", flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 300)
