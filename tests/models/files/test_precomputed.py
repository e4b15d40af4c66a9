import logging
import os
from pathlib import Path

import helpers
import kapture
import kapture.io.csv
import kapture.io.features
import numpy as np
import pytest
from hydra.utils import instantiate

from locretrieval.models import PrecomputedDescriptor
from locretrieval.retrieval.descriptors import describe_scene
from locretrieval.scene import Camera, ImageSet, Scene

DATABASE = ["mapping/cam0/0001.jpg", "mapping/cam0/0002.jpg", "mapping/cam1/0001.jpg", "mapping/cam1/0002.jpg"]
QUERIES = ["query/day/q1.jpg", "query/night/q2.jpg"]


def write_global_features(
    kapture_dir: Path, feature_name: str, vectors: dict[str, np.ndarray], dsize: int | None = None
) -> Path:
    """A kapture global-features folder written with kapture's own writers; returns the folder."""
    dtype = next(iter(vectors.values())).dtype.type
    dsize = dsize or len(next(iter(vectors.values())))
    config = kapture.io.csv.get_feature_csv_fullpath(kapture.GlobalFeatures, feature_name, str(kapture_dir))
    kapture.io.csv.global_features_to_file(config, kapture.GlobalFeatures(feature_name, dtype, dsize, "L2"))
    for image_name, vector in vectors.items():
        path = kapture.io.features.get_global_features_fullpath(feature_name, str(kapture_dir), image_name)
        kapture.io.features.image_global_features_to_file(path, vector)
    return kapture_dir / "reconstruction" / "global_features" / feature_name


def image_set(names: list[str], root: Path) -> ImageSet:
    camera = Camera("SIMPLE_PINHOLE", 64, 48, (50.0, 32.0, 24.0))
    count = len(names)
    return ImageSet(names, root, [camera] * count, np.tile([1.0, 0, 0, 0], (count, 1)), np.zeros((count, 3)))


def random_vectors(names: list[str], dim: int, seed: int, dtype=np.float32) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {name: (3.0 * rng.normal(size=dim)).astype(dtype) for name in names}


def normalised(vectors: dict[str, np.ndarray], names: list[str]) -> np.ndarray:
    rows = np.stack([vectors[name].astype(np.float64) for name in names])
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def test_single_folder_reads_back_what_kapture_wrote(tmp_path, caplog):
    vectors = random_vectors(DATABASE + QUERIES, 16, seed=0)
    folder = write_global_features(tmp_path / "dataset", "Resnet101-AP-GeM", vectors)
    model = helpers.precomputed(path=str(folder))
    assert model.name == "Resnet101-AP-GeM"  # from global_features.txt
    images = image_set(QUERIES + DATABASE[:2], tmp_path / "dataset" / "sensors" / "records_data")
    with caplog.at_level(logging.INFO, logger="locretrieval.models.files.precomputed"):
        descriptors = model.describe(images)
    assert descriptors.dtype == np.float32 and descriptors.shape == (4, 16)
    np.testing.assert_allclose(descriptors, normalised(vectors, images.names), atol=1e-6)
    assert "4 of 4 global features were not L2-normalised" in caplog.text


def test_float64_features_are_read_as_float32(tmp_path):
    vectors = random_vectors(DATABASE, 8, seed=1, dtype=np.float64)
    folder = write_global_features(tmp_path, "dense", vectors)
    descriptors = helpers.precomputed(path=folder, name="dense").describe(image_set(DATABASE, tmp_path))
    assert descriptors.dtype == np.float32
    np.testing.assert_allclose(descriptors, normalised(vectors, DATABASE), atol=1e-6)


@pytest.fixture
def mapping_and_query(tmp_path) -> tuple[Scene, dict[str, np.ndarray], list[Path]]:
    """NAVER's layout: mapping and query kaptures, each with its own global-features folder."""
    vectors = random_vectors(DATABASE + QUERIES, 12, seed=2)
    folders = [
        write_global_features(tmp_path / "mapping", "apgem", {n: vectors[n] for n in DATABASE}),
        write_global_features(tmp_path / "query", "apgem", {n: vectors[n] for n in QUERIES}),
    ]
    scene = Scene(
        "two-kaptures",
        image_set(DATABASE, tmp_path / "mapping" / "sensors" / "records_data"),
        image_set(QUERIES, tmp_path / "query" / "sensors" / "records_data"),
        sources=[tmp_path / "mapping", tmp_path / "query"],
    )
    return scene, vectors, folders


@pytest.mark.parametrize("how", ["path_list", "sources_by_name", "sources_single_type"])
def test_mapping_and_query_folders(tmp_path, mapping_and_query, how):
    scene, vectors, folders = mapping_and_query
    model = {
        "path_list": lambda: helpers.precomputed(path=[str(f) for f in folders]),
        "sources_by_name": lambda: helpers.precomputed(feature_name="apgem"),
        "sources_single_type": lambda: helpers.precomputed(),
    }[how]()
    database, queries = describe_scene(model, scene, tmp_path / "cache")
    assert model.name == "apgem"
    assert [f.resolve() for f in model.folders] == [f.resolve() for f in folders]
    np.testing.assert_allclose(database, normalised(vectors, DATABASE), atol=1e-6)
    np.testing.assert_allclose(queries, normalised(vectors, QUERIES), atol=1e-6)


def test_cache_invalidates_when_the_files_change(tmp_path, mapping_and_query):
    scene, vectors, folders = mapping_and_query
    before, _ = describe_scene(helpers.precomputed(feature_name="apgem"), scene, tmp_path / "cache")
    again, _ = describe_scene(helpers.precomputed(feature_name="apgem"), scene, tmp_path / "cache")
    np.testing.assert_array_equal(again, before)
    changed = folders[0] / f"{DATABASE[1]}.gfeat"
    kapture.io.features.image_global_features_to_file(str(changed), -vectors[DATABASE[1]])
    stat = changed.stat()
    os.utime(changed, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))  # coarse file-system clocks
    after, _ = describe_scene(helpers.precomputed(feature_name="apgem"), scene, tmp_path / "cache")
    np.testing.assert_allclose(after[1], -before[1], atol=1e-6)
    np.testing.assert_array_equal(np.delete(after, 1, axis=0), np.delete(before, 1, axis=0))
    assert len(list((tmp_path / "cache" / "descriptors").glob("*.npz"))) == 2


def test_missing_feature_file_names_image_and_folders(tmp_path):
    folder = write_global_features(tmp_path, "apgem", random_vectors(DATABASE[:3], 8, seed=3))
    with pytest.raises(FileNotFoundError, match=r"'mapping/cam1/0002\.jpg'.*searched \[.*apgem'\]"):
        helpers.precomputed(path=folder).describe(image_set(DATABASE, tmp_path))


def test_wrong_file_size_names_file_and_byte_counts(tmp_path):
    vectors = random_vectors(DATABASE, 8, seed=4)
    vectors[DATABASE[2]] = vectors[DATABASE[2]][:6]
    folder = write_global_features(tmp_path, "apgem", vectors, dsize=8)
    with pytest.raises(ValueError, match=r"cam1/0001\.jpg\.gfeat: 24 bytes, expected 32 \(8 x float32\)"):
        helpers.precomputed(path=folder).describe(image_set(DATABASE, tmp_path))


def test_inconsistent_dimensions_between_folders(tmp_path):
    first = write_global_features(tmp_path / "mapping", "apgem", random_vectors(DATABASE, 8, seed=5))
    second = write_global_features(tmp_path / "query", "apgem", random_vectors(QUERIES, 16, seed=6))
    message = r"inconsistent global features: .*mapping.* 8 x float32, .*query.* 16 x float32"
    with pytest.raises(ValueError, match=message):
        helpers.precomputed(path=[first, second])


def test_non_finite_and_zero_features_are_errors(tmp_path):
    vectors = random_vectors(DATABASE, 8, seed=7)
    vectors[DATABASE[1]][3] = np.nan
    folder = write_global_features(tmp_path / "nan", "apgem", vectors)
    with pytest.raises(ValueError, match=r"cam0/0002\.jpg\.gfeat: global feature holds non-finite values"):
        helpers.precomputed(path=folder).describe(image_set(DATABASE, tmp_path))
    vectors[DATABASE[1]][:] = 0.0
    folder = write_global_features(tmp_path / "zero", "apgem", vectors)
    with pytest.raises(ValueError, match=r"cam0/0002\.jpg\.gfeat: global feature is all zeros"):
        helpers.precomputed(path=folder).describe(image_set(DATABASE, tmp_path))


def test_folder_errors(tmp_path, mapping_and_query):
    scene, _, _ = mapping_and_query
    absent = helpers.precomputed(path=tmp_path / "nowhere")  # built: its missing inputs are named before any work
    assert absent.missing_inputs(scene) == [f"path: global features {tmp_path}/nowhere/global_features.txt not found"]
    with pytest.raises(FileNotFoundError, match=r"global_features header not found: .*nowhere/global_features\.txt"):
        absent.describe(scene.queries)
    assert helpers.precomputed(feature_name="apgem").missing_inputs(scene) == []
    assert (
        helpers.precomputed(feature_name="netvlad")
        .missing_inputs(scene)[0]
        .startswith("feature_name: no global features 'netvlad': searched")
    )
    with pytest.raises(FileNotFoundError, match=r"no global features 'netvlad': searched .*mapping.*query"):
        describe_scene(helpers.precomputed(feature_name="netvlad"), scene, None)
    write_global_features(tmp_path / "mapping", "netvlad", random_vectors(DATABASE, 4, seed=8))
    with pytest.raises(ValueError, match=r"2 global-feature types \['apgem', 'netvlad'\]"):
        describe_scene(helpers.precomputed(), scene, None)
    with pytest.raises(RuntimeError, match="no feature folders"):
        helpers.precomputed(feature_name="apgem").describe(scene.queries)


def precomputed_config(tmp_path, *overrides):
    """``evaluate.yaml`` with ``model=precomputed`` and its Hydra node, composed by Hydra."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(helpers.CONFIGS), version_base="1.3"):
        return compose(
            config_name="evaluate",
            overrides=["model=precomputed", f"paths.root_dir={tmp_path}", *overrides],
            return_hydra_config=True,
        )


@pytest.mark.parametrize(
    ("overrides", "name"), [([], "precomputed"), (["model.feature_name=AP-GeM-LM18"], "AP-GeM-LM18")]
)
def test_config_names_the_ranking_and_output_folder(overrides, name, tmp_path):
    cfg = precomputed_config(tmp_path, *overrides)
    assert cfg.model.name == name
    assert cfg.hydra.run.dir.split("/")[-2] == name


def test_a_feature_folder_names_the_ranking_unless_a_name_is_given(tmp_path):
    vectors = random_vectors(DATABASE + QUERIES, 8, seed=9)
    folders = {name: write_global_features(tmp_path / name, name, vectors) for name in ("AP-GeM-LM18", "NetVLAD")}
    names = []
    for folder in folders.values():  # the two runs of `-m model.path=<AP-GeM-LM18>,<NetVLAD>`
        cfg = precomputed_config(tmp_path, f"model.path={folder}")
        model = instantiate(cfg.model)
        assert model.name == cfg.model.name == folder.name and cfg.hydra.run.dir.split("/")[-2] == folder.name
        names.append(model.name)
    assert names == ["AP-GeM-LM18", "NetVLAD"]
    mapping = write_global_features(tmp_path / "mapping", "apgem", {n: vectors[n] for n in DATABASE})
    query = write_global_features(tmp_path / "query", "apgem", {n: vectors[n] for n in QUERIES})
    assert instantiate(precomputed_config(tmp_path, f"model.path=[{mapping},{query}]").model).name == "apgem"
    named = precomputed_config(tmp_path, f"model.path={folders['NetVLAD']}", "model.name=mine")
    assert instantiate(named.model).name == "mine"
    assert (
        PrecomputedDescriptor(name=None, path=folders["NetVLAD"], feature_name=None, allow_integer=False).name
        == "NetVLAD"
    )  # the Python API names it alike


def write_hloc(path: Path, vectors: dict[str, np.ndarray]) -> Path:
    """hloc's global-features file: a ``global_descriptor`` in the group of each image name."""
    import h5py

    with h5py.File(path, "w") as file:
        for name, vector in vectors.items():
            file.create_group(name).create_dataset("global_descriptor", data=vector)
    return path


def test_hloc_files_are_read_by_image_name_from_the_first_file_holding_it(tmp_path):
    database, queries = random_vectors(DATABASE, 8, seed=1), random_vectors(QUERIES, 8, seed=2, dtype=np.float16)
    files = [write_hloc(tmp_path / "global-feats-netvlad-db.h5", database),
             write_hloc(tmp_path / "global-feats-netvlad-query.h5", queries)]  # fmt: skip
    model = helpers.precomputed(path=[str(file) for file in files])
    assert model.name == "global-feats-netvlad-db+global-feats-netvlad-query"  # the files' names, without .h5
    images = image_set(QUERIES + DATABASE, tmp_path)
    np.testing.assert_allclose(model.describe(images), normalised({**database, **queries}, images.names), atol=1e-6)
    assert model.identity()["hloc_files"] == [str(file.resolve()) for file in files]
    scene = Scene("s", image_set(DATABASE, tmp_path), image_set(QUERIES, tmp_path))
    assert model.missing_inputs(scene) == []
    with pytest.raises(
        KeyError, match=r"global-feats-netvlad-db.h5, .*-query.h5: no global_descriptor for image 'x.jpg'"
    ):
        model.describe(image_set(["x.jpg"], tmp_path))
    absent = helpers.precomputed(path=str(tmp_path / "absent.h5"))
    assert absent.missing_inputs(scene) == [f"path: hloc global features {tmp_path / 'absent.h5'} not found"]
    with pytest.raises(ValueError, match="model.path mixes hloc files and kapture folders"):
        helpers.precomputed(path=[str(files[0]), str(tmp_path)])
    write_hloc(tmp_path / "zeros.h5", {name: np.zeros(8, np.float32) for name in DATABASE})
    with pytest.raises(ValueError, match=r"zeros.h5: image 'mapping/cam0/0001.jpg': global feature is all zeros"):
        helpers.precomputed(path=str(tmp_path / "zeros.h5")).describe(image_set(DATABASE, tmp_path))
