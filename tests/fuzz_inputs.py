"""Fuzzing of the files the benchmark reads (run by tests/whole/test_fuzz_inputs.py in its own interpreter).

Seeded hypothesis strategies mutate, byte by byte and field by field, each kapture text file (and
an image) of a small valid folder, a revisited ground-truth pickle and a cache ``.npz``, and build
the inputs that once crashed or exhausted the interpreter (#61): pickles nested deep or sharing
references (through the plain and the torch loader), archives of every compression ratio
(``.npz`` members, MATLAB elements and cells), hloc HDF5 files with links, external storage and
unwritten datasets, and YAML with aliases; and (#69) each file of a COLMAP model as published ones
are (a rig, distortion, 3D points; binary and text: bytes, fields, counts and values such as NaN or
2^64 - 1) and photo folders (links that loop, lead out or nowhere, a header of 13,000 x 13,000
pixels, damaged photos, GPS altitudes out of range). Every case must end in a result or in the
project's error naming the file (`DataFileError`, ``FileNotFoundError`` for a listed file that is
absent, or the error a loader documents), never another exception, a hang or a crash of this
interpreter; a COLMAP model that loads must be valid (`invalid_model`). Prints how many cases each
target tried, the peak resident memory and each target's largest case (the memory it took above
what was resident before it):
``fuzz: N cases (kapture K, gnd G, ...); peak memory M MiB; largest case (...): kapture X, ...``.

    python tests/fuzz_inputs.py [EXAMPLES_PER_TARGET]   # the new targets try a fifth as many (each costs more)
"""

import functools
import io
import logging
import pickle
import struct
import sys
import tempfile
import warnings
import zipfile
from collections import Counter
from pathlib import Path

import h5py
import numpy as np
import scipy.io
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from locretrieval.cache import load_arrays, save_arrays
from locretrieval.errors import DataFileError
from locretrieval.metrics.revisited import PROTOCOLS, load_revisited_groundtruth
from locretrieval.models.files.feature_io import read_hloc_global_descriptors
from locretrieval.models.files.weights import load_torch_file
from locretrieval.models.published.netvlad import read_netvlad_struct
from locretrieval.report.run_files import load_yaml
from locretrieval.restricted_pickle import load_plain_pickle
from locretrieval.scene.colmap import read_model
from locretrieval.scene.kapture_io import load_image_set
from locretrieval.scene.photos import checked_photos
from locretrieval.scene.scale import gps_positions

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the tests' own builders
from own_place import plain_photos, rig_model  # noqa: E402

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
#: The most memory one case of each target took, MiB (`expect_named`).
CASE_PEAKS: Counter = Counter()
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


def expect_named(call, path: Path, target: str, documented: tuple[type[Exception], ...] = ()):
    """``call()``'s result; a `DataFileError`, ``FileNotFoundError`` or ``documented`` error naming ``path``
    counts as handled. The memory the call took above what was resident before it is kept, the
    largest per target (`CASE_PEAKS`, MiB)."""
    CASES[target] += 1
    resident = reset_peak_kib()
    try:
        return call()
    except (DataFileError, FileNotFoundError, *documented) as error:
        if str(path) not in str(error):
            raise AssertionError(f"{target}: the error does not name {path}: {error}") from error
        return None
    finally:
        CASE_PEAKS[target] = max(CASE_PEAKS[target], (status_kib("VmHWM") - resident) / 1024)


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


# --- the inputs that crashed or exhausted the interpreter (#61) ------------------------------------


def nested(kind: str, depth: int):
    """0 in ``depth`` containers of ``kind``: tuples (``key``: as a dict's key), lists, dicts or frozensets."""
    wrap = {"tuple": lambda v: (v,), "key": lambda v: (v,), "list": lambda v: [v], "value": lambda v: {"k": v}}
    value: object = 0
    for _ in range(depth):
        value = frozenset([value]) if kind == "frozenset" else wrap[kind](value)
    return {value: 1} if kind == "key" else value


def laughs(levels: int, fan_out: int):
    """``fan_out ** levels`` leaves sharing ``levels`` lists."""
    value: object = 0
    for _ in range(levels):
        value = [value] * fan_out
    return value


@given(
    shape=st.sampled_from(["tuple", "list", "key", "value", "frozenset", "raw tuples", "laughs"]),
    depth=st.integers(0, 150) | st.sampled_from([10**3, 10**5, 10**6]),
    fan_out=st.integers(2, 12),
    protocol=st.integers(0, pickle.HIGHEST_PROTOCOL),
    mutation=byte_mutation(),
    mutate=st.booleans(),
    torch_file=st.booleans(),
)
def fuzz_nesting(shape, depth, fan_out, protocol, mutation, mutate, torch_file):
    if shape == "raw tuples":  # the reproduction: a dict key nested ``depth`` deep, hashed while unpickling
        data = b"\x80\x02})" + b"\x85" * depth + b"Ns."
    else:
        content = laughs(min(depth, 12), fan_out) if shape == "laughs" else nested(shape, min(depth, 150))
        stream = io.BytesIO()
        if torch_file:
            torch.save({"architecture": content}, stream, pickle_protocol=max(protocol, 2))
        else:
            pickle.dump(content, stream, protocol=protocol)
        data = stream.getvalue()
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / ("weights.pt" if torch_file else "gnd_roxford5k.pkl")
        path.write_bytes(mutate_bytes(data, mutation) if mutate else data)
        expect_named(lambda: (load_torch_file if torch_file else load_plain_pickle)(path), path, "nesting")


def npy_bytes(array: np.ndarray, claimed: tuple[int, ...] | None) -> bytes:
    """``array`` as an ``.npy`` file whose header may claim another shape."""
    stream = io.BytesIO()
    np.save(stream, array)
    data = stream.getvalue()
    if claimed is None:
        return data
    header = np.lib.format.header_data_from_array_1_0(array) | {"shape": claimed}
    text = repr(header).encode().ljust(117) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text + array.tobytes()


@given(
    kind=st.sampled_from(["npz", "mat", "mat cells"]),
    size=st.sampled_from([0, 1, 100, 2**12, 2**16, 2**19]),  # 2**19 zeros: 4 MB in 4 kB, past the budget
    zeros=st.booleans(),
    compressed=st.booleans(),
    claimed=st.none() | st.tuples(st.sampled_from([0, 1, 7, 2**20, 10**12])),
    mutation=byte_mutation(),
    mutate=st.booleans(),
)
def fuzz_compression(kind, size, zeros, compressed, claimed, mutation, mutate):
    array = np.zeros(size) if zeros else np.random.default_rng(size).normal(size=size)
    with tempfile.TemporaryDirectory() as folder:
        if kind == "npz":
            path = Path(folder) / "cache.npz"
            with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED if compressed else zipfile.ZIP_STORED) as archive:
                archive.writestr("descriptors.npy", npy_bytes(array, claimed))
            call, documented = (lambda: load_arrays(path)), ()
        else:
            path = Path(folder) / "Pitts30K_struct.mat"
            content = array
            if kind == "mat cells":
                content = np.empty((1, 2), dtype=object)
                content[0, 0], content[0, 1] = array[:8], array[:4]
            scipy.io.savemat(path, {"net": content}, do_compression=compressed)
            if claimed is not None and kind == "mat cells" and not compressed:
                data = bytearray(path.read_bytes())
                data[160:168] = struct.pack("<ii", 1, min(claimed[0], 2**31 - 1))  # the cell array's dimensions
                path.write_bytes(data)
            call, documented = (lambda: read_netvlad_struct(path)), (ValueError,)  # not NetVLAD's struct: named
        if mutate:
            path.write_bytes(mutate_bytes(path.read_bytes(), mutation))
        expect_named(call, path, "compression", documented)


@given(
    layouts=st.lists(
        st.sampled_from(["dataset", "float16", "external link", "soft link", "hard link", "external storage",
                         "unwritten", "unwritten small", "compressed", "not a group"]),
        min_size=1, max_size=4,
    ),
    mutation=byte_mutation(),
    mutate=st.booleans(),
)  # fmt: skip
def fuzz_hdf5(layouts, mutation, mutate):
    with tempfile.TemporaryDirectory() as folder:
        other, raw, path = Path(folder) / "other.h5", Path(folder) / "other.raw", Path(folder) / "features.h5"
        with h5py.File(other, "w") as file:
            file.create_dataset("x/global_descriptor", data=np.ones(4, dtype=np.float32))
        raw.write_bytes(np.ones(4, dtype=np.float32).tobytes())
        names = [f"img{i}.jpg" for i in range(len(layouts))]
        with h5py.File(path, "w") as file:
            for name, layout in zip(names, layouts):
                node = f"{name}/global_descriptor"
                if layout in ("dataset", "float16", "compressed"):
                    dtype = np.float16 if layout == "float16" else np.float32
                    file.create_dataset(
                        node, data=np.arange(4, dtype=dtype), compression="gzip" if layout == "compressed" else None
                    )
                elif layout == "external link":
                    file[name] = h5py.ExternalLink(str(other), "x")
                elif layout == "soft link":
                    file[name] = h5py.SoftLink(f"/{names[0]}")
                elif layout == "hard link" and layouts[0] in ("dataset", "float16", "compressed") and name != names[0]:
                    file[name] = file[names[0]]
                elif layout == "external storage":
                    file.create_dataset(node, shape=(4,), dtype=np.float32, external=[(str(raw), 0, 16)])
                elif layout.startswith("unwritten"):
                    size = 2**10 if layout == "unwritten small" else 2**27
                    file.create_dataset(
                        node, shape=(size,), dtype=np.float32, chunks=(min(size, 2**16),), compression="gzip"
                    )
                else:
                    file.create_dataset(name, data=np.zeros(2))
        if mutate:
            path.write_bytes(mutate_bytes(path.read_bytes(), mutation))
        documented = (KeyError, ValueError)  # no descriptor for an image; descriptors of different sizes
        expect_named(lambda: read_hloc_global_descriptors(path, names), path, "hdf5", documented)


CONFIG_YAML = (
    "report:\n  gallery: {queries: selected, k: 5, worst: 10, random: 5, seed: 0, thumbnail_size: 160}\n"
    "paths: {cache_dir: ${oc.env:HOME}}\nsfm:\n  features: {_target_: locretrieval.sfm.features.SiftFeatures}\n"
)


@given(
    shape=st.sampled_from(["aliases", "merge keys", "nested", "config"]),
    levels=st.integers(0, 12),
    fan_out=st.integers(1, 12),
    mutation=byte_mutation(),
    mutate=st.booleans(),
)
def fuzz_yaml(shape, levels, fan_out, mutation, mutate):
    if shape == "aliases":
        lines = ["l0: &l0 [x]"] + [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * fan_out)}]" for i in range(1, levels + 1)]
        text = "\n".join(lines) + "\n"
    elif shape == "merge keys":
        lines = ["m0: &m0 {a: 1}"] + [
            f"m{i}: &m{i} {{<<: [{', '.join([f'*m{i - 1}'] * fan_out)}], k{i}: {i}}}" for i in range(1, levels + 1)
        ]
        text = "\n".join(lines) + "\n"
    elif shape == "nested":
        text = "a: " + "[" * (levels * fan_out * 3) + "]" * (levels * fan_out * 3) + "\n"  # past the recursion limit
    else:
        text = CONFIG_YAML
    data = text.encode()
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "config.yaml"
        path.write_bytes(mutate_bytes(data, mutation) if mutate else data)
        expect_named(lambda: load_yaml(path), path, "yaml")


# --- COLMAP models and photo folders (#69) -----------------------------------------------------------

#: Values a careless or hostile writer puts in a binary COLMAP field: (struct format, value).
BINARY_VALUES = [
    *(("<d", value) for value in (float("nan"), float("inf"), -float("inf"), 0.0, -1.0, 2.0, 1e300, 1e-300)),
    *(("<Q", value) for value in (0, 1, 2**32, 2**40, 2**63, 2**64 - 1)),
    *(("<I", value) for value in (0, 1, 7, 2**31, 2**32 - 1)),
    *(("<i", value) for value in (-1, 3, 17, 99, 2**31 - 1)),
]
#: ... and in a text one's fields.
COLMAP_TOKENS = [
    *TOKENS, "1e999", "-0", "4294967295", "18446744073709551615", "CAMERA", "IMU", "OPENCV", "EQUIRECTANGULAR",
    "1 2 3", "", "\xe9.jpg",
]  # fmt: skip


@functools.cache
def colmap_models() -> dict[str, dict[str, bytes]]:
    """The files of a model as published ones are (`own_place.rig_model`: a rig of two cameras,
    distortion, keypoints, 3D points), binary and text, by file name."""
    with tempfile.TemporaryDirectory() as folder:
        return {
            kind: {
                path.name: path.read_bytes() for path in rig_model(Path(folder) / kind, text=kind == "text").iterdir()
            }
            for kind in ("binary", "text")
        }


def invalid_model(reconstruction) -> str | None:
    """Why a model that loaded is not one to benchmark (a camera's focal length not positive or
    its principal point outside the image, a parameter or a registered pose not finite, a rotation
    not a unit quaternion, a name not text), checked independently of the loader; None when valid."""
    for camera_id, camera in reconstruction.cameras.items():
        params = np.asarray(camera.params, dtype=np.float64)
        focal, centre = params[camera.focal_length_idxs()], params[camera.principal_point_idxs()]
        if not (np.isfinite(params).all() and (focal > 0).all()):
            return f"camera {camera_id}: {params}"
        if not (0 <= centre[0] <= camera.width and 0 <= centre[1] <= camera.height):
            return f"camera {camera_id}: principal point {centre} outside {camera.width} x {camera.height}"
    for image_id, image in reconstruction.images.items():
        image.name.encode()  # a name pycolmap cannot decode raises here
        if image.has_pose:
            pose = image.cam_from_world()
            quaternion, translation = np.asarray(pose.rotation.quat), np.asarray(pose.translation)
            if not (np.isfinite(translation).all() and abs(np.linalg.norm(quaternion) - 1.0) <= 1e-3):
                return f"image {image_id}: pose {quaternion} {translation}"
    return None


@given(
    kind=st.sampled_from(["binary", "text"]),
    file=st.sampled_from(["rigs", "cameras", "frames", "images", "points3D"]),
    mutation=byte_mutation(),
    field=st.tuples(st.floats(0, 1), st.floats(0, 1), st.sampled_from(COLMAP_TOKENS) | st.text(max_size=12)),
    value=st.tuples(st.floats(0, 1), st.sampled_from(BINARY_VALUES)),
    by_field=st.booleans(),
)
def fuzz_colmap(kind, file, mutation, field, value, by_field):
    files = dict(colmap_models()[kind])
    name = f"{file}.{'bin' if kind == 'binary' else 'txt'}"
    if by_field and kind == "binary":
        fraction, (layout, number) = value
        data = bytearray(files[name])
        offset = int(fraction * max(0, len(data) - struct.calcsize(layout)))
        if len(data) >= struct.calcsize(layout):
            struct.pack_into(layout, data, offset, number)
        files[name] = bytes(data)
    elif by_field:
        files[name] = mutate_token(files[name].decode(), *field).encode("utf-8", "surrogatepass")
    else:
        files[name] = mutate_bytes(files[name], mutation)
    with tempfile.TemporaryDirectory() as folder:
        model = Path(folder) / "sparse"
        model.mkdir()
        for file_name, content in files.items():
            (model / file_name).write_bytes(content)
        reconstruction = expect_named(lambda: read_model(model), model, "colmap")
        if reconstruction is not None and (problem := invalid_model(reconstruction)) is not None:
            raise AssertionError(f"colmap: an invalid model loaded ({problem})")


def mutate_token(text: str, line_fraction: float, token_fraction: float, value: str) -> str:
    """``text`` with one space-separated token of one line replaced by ``value``."""
    lines = text.split("\n")
    number = int(line_fraction * (len(lines) - 1))
    tokens = lines[number].split(" ")
    tokens[int(token_fraction * (len(tokens) - 1))] = value
    lines[number] = " ".join(tokens)
    return "\n".join(lines)


#: What a shared photo folder may hold besides photos (a file name -> what it is): links that loop,
#: lead out or nowhere, a hidden file, another file, a PNG header declaring 13,000 x 13,000 pixels.
PHOTO_EXTRAS = ["loop", "up", "outside", "outside.jpg", "nowhere.jpg", ".hidden.jpg", "notes.txt", "huge.png"]


def huge_png() -> bytes:
    """A PNG whose header declares 13,000 x 13,000 pixels, its data cut short."""
    stream = io.BytesIO()
    Image.new("1", (8, 8)).save(stream, format="PNG")
    data = bytearray(stream.getvalue())
    struct.pack_into(">II", data, 16, 13_000, 13_000)  # IHDR's width and height (its CRC left wrong)
    return bytes(data)


@given(
    photos=st.integers(0, 4),
    extras=st.lists(st.sampled_from(PHOTO_EXTRAS), max_size=4, unique=True),
    mutation=byte_mutation(),
    mutate=st.booleans(),
    altitude=st.none() | st.sampled_from([0.0, -1e6, 4294967295.0, 1e300]),
)
def fuzz_photos(photos, extras, mutation, mutate, altitude):
    with tempfile.TemporaryDirectory() as root:
        folder, outside = Path(root) / "photos", Path(root) / "shared"
        names = plain_photos(folder, np.arange(3.0 * photos).reshape(-1, 3), 16, 12, [altitude] * photos)
        plain_photos(outside, np.ones((1, 3)), 16, 12)
        folder.mkdir(exist_ok=True)
        if mutate and names:
            (folder / names[0]).write_bytes(mutate_bytes((folder / names[0]).read_bytes(), mutation))
        links = {"loop": ".", "up": "..", "outside": outside, "outside.jpg": outside / "walk/000.jpg",
                 "nowhere.jpg": Path(root) / "nowhere.jpg"}  # fmt: skip
        for extra in extras:
            if extra in links:
                (folder / extra).symlink_to(links[extra])
            else:
                (folder / extra).write_bytes(huge_png() if extra == "huge.png" else b"not a photo")
        found = expect_named(lambda: checked_photos(folder), folder, "photos")
        if found is not None:
            gps_positions(folder, found)  # GPS that cannot be read counts as none


#: Targets and the share of ``EXAMPLES_PER_TARGET`` each tries (a case of the newer ones costs about 3x).
TARGETS = {
    fuzz_kapture: 1.0, fuzz_groundtruth: 1.0, fuzz_cache: 1.0,
    fuzz_nesting: 0.3, fuzz_compression: 0.3, fuzz_hdf5: 0.3, fuzz_yaml: 0.3, fuzz_colmap: 0.3, fuzz_photos: 0.2,
}  # fmt: skip


def main(examples: int) -> None:
    logging.disable(logging.WARNING)  # the loaders' warnings about odd but usable files
    warnings.filterwarnings("ignore", message="Detected pickle protocol")  # torch's, of the protocols tried
    for fuzz, share in TARGETS.items():
        settings(SETTINGS, max_examples=max(1, round(share * examples)))(fuzz)()
    reset_peak_kib()  # the last case's peak
    counts = ", ".join(f"{target} {count}" for target, count in CASES.items())
    peaks = ", ".join(f"{target} {peak:.1f}" for target, peak in CASE_PEAKS.items())
    print(
        f"fuzz: {sum(CASES.values())} cases ({counts}); peak memory {PEAK_KIB / 1024:.0f} MiB; "
        f"largest case (MiB above the resident memory before it): {peaks}",
        flush=True,
    )


#: This process's peak resident memory (KiB) before the last `reset_peak_kib`.
PEAK_KIB = 0


def reset_peak_kib() -> int:
    """This process's resident memory now (KiB), its peak (``VmHWM``) reset to it (Linux 4.0+:
    ``/proc/self/clear_refs``), the peak so far kept in `PEAK_KIB`."""
    global PEAK_KIB
    PEAK_KIB = max(PEAK_KIB, status_kib("VmHWM"))
    with open("/proc/self/clear_refs", "w") as control:
        control.write("5")
    return status_kib("VmRSS")


def status_kib(key: str) -> int:
    """A memory figure of ``/proc/self/status`` (KiB): ``VmHWM`` the peak resident memory (which
    starts anew with the program: ``ru_maxrss`` keeps the peak of the process that started it
    across ``exec``), ``VmRSS`` the resident memory now."""
    for line in open("/proc/self/status"):
        if line.startswith(f"{key}:"):
            return int(line.split()[1])
    raise KeyError(key)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 300)
