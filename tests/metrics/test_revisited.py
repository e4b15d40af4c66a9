import pickle

import numpy as np
import pytest
from helpers import ObjectPointerArray, error_in_subprocess

from locretrieval.errors import DataFileError
from locretrieval.metrics.revisited import REVISITED_COLUMNS, evaluate_revisited, load_revisited_groundtruth
from locretrieval.restricted_pickle import RefusedGlobalError, RefusedPickleError
from locretrieval.retrieval import EMPTY, Ranking

# 8 database images, 2 queries.
# q0: easy {0, 3}, hard {5}, junk {1}; ranking 1 0 2 5 3 4 6 7.
# q1: easy {}, hard {2}, junk {}; ranking 2 0 1 3 4 5 6 7.
GROUNDTRUTH = {
    "imlist": [f"db{i}" for i in range(8)],
    "qimlist": ["q0", "q1"],
    "gnd": [
        {"easy": [0, 3], "hard": [5], "junk": [1], "bbx": [0, 0, 10, 10]},
        {"easy": [], "hard": [2], "junk": [], "bbx": [0, 0, 10, 10]},
    ],
}
RANKING = np.array([[1, 0, 2, 5, 3, 4, 6, 7], [2, 0, 1, 3, 4, 5, 6, 7]])


@pytest.fixture
def groundtruth(tmp_path):
    path = tmp_path / "gnd_toy.pkl"
    path.write_bytes(pickle.dumps(GROUNDTRUTH))
    return load_revisited_groundtruth(path)


def test_protocols_match_hand_computed_values(groundtruth):
    table = evaluate_revisited(
        Ranking("toy", RANKING, np.zeros(RANKING.shape), "descriptor"), groundtruth, "toy", kappas=(1, 5, 10)
    )
    assert list(table.columns) == REVISITED_COLUMNS
    value = table.set_index(["protocol", "metric", "k"])["value"]
    count = table.set_index(["protocol", "metric", "k"])["num_queries"]
    # Medium, q0: positives {0, 3, 5}, junk {1}: without junk the order is 0 2 5 3 4 6 7,
    # positives at ranks 0, 2, 3 -> AP = (1 + (1/2 + 2/3)/2 + (2/3 + 3/4)/2) / 3 = 55/72.
    assert value[("medium", "map", 0)] == pytest.approx((55 / 72 + 1.0) / 2)  # q1: hard {2} ranked first
    # Easy, q0: positives {0, 3}, junk {1, 5}: order 0 2 3 4 6 7 -> ranks 0, 2 -> 19/24; q1 has no
    # easy positive and is left out.
    assert value[("easy", "map", 0)] == pytest.approx(19 / 24) and count[("easy", "map", 0)] == 1
    # Hard, q0: positive {5}, junk {1, 0, 3}: order 2 5 4 6 7 -> rank 1 -> (0/1 + 1/2)/2 = 1/4.
    assert value[("hard", "map", 0)] == pytest.approx((1 / 4 + 1.0) / 2) and count[("hard", "map", 0)] == 2
    # mP@k: k' = min(k, 1-based position of the last positive). Medium q0: positives at
    # 1, 3, 4 -> P@1 = 1, P@5 = P@10 = 3/4 (k' = 4); q1: positive at 1 -> 1, 1, 1.
    assert value[("medium", "mp", 1)] == pytest.approx(1.0)
    assert value[("medium", "mp", 5)] == pytest.approx((3 / 4 + 1) / 2)
    assert value[("medium", "mp", 10)] == pytest.approx((3 / 4 + 1) / 2)
    # Hard q0: positive at 2 -> P@1 = 0/1, P@5 = 1/2.
    assert value[("hard", "mp", 1)] == pytest.approx((0 + 1) / 2)
    assert value[("hard", "mp", 5)] == pytest.approx((1 / 2 + 1) / 2)


def test_a_truncated_ranking_counts_missing_positives_as_not_retrieved(groundtruth):
    truncated = Ranking("toy", [[1, 0, 2, EMPTY], [0, 1, 3, EMPTY]], np.zeros((2, 4)), "descriptor")
    value = evaluate_revisited(truncated, groundtruth, "toy").set_index(["protocol", "metric", "k"])["value"]
    # Medium q0: only positive 0 retrieved (rank 0 after junk) of 3 -> AP 1/3; q1: positive 2
    # not retrieved -> AP 0, P@k 0.
    assert value[("medium", "map", 0)] == pytest.approx((1 / 3 + 0) / 2)
    assert value[("medium", "mp", 1)] == pytest.approx((1 + 0) / 2)


def test_malformed_files_are_reported_with_their_path(tmp_path):
    with pytest.raises(FileNotFoundError, match="gnd_roxford5k.pkl"):
        load_revisited_groundtruth(tmp_path / "missing.pkl")
    bad = tmp_path / "bad.pkl"
    bad.write_bytes(pickle.dumps({"imlist": [], "gnd": []}))
    with pytest.raises(ValueError, match="bad.pkl.*qimlist"):
        load_revisited_groundtruth(bad)
    outside = tmp_path / "outside.pkl"
    outside.write_bytes(pickle.dumps({**GROUNDTRUTH, "imlist": ["db0", "db1"]}))
    with pytest.raises(ValueError, match="outside.pkl.*q0"):
        load_revisited_groundtruth(outside)


def _published_structure() -> dict:
    """A ``gnd_*.pkl`` content with numpy arrays where the authors' files may hold them."""
    return {
        "imlist": [f"db{i}" for i in range(8)],
        "qimlist": ["q0", "q1"],
        "gnd": [
            {
                "easy": np.array([0, 3]),
                "hard": np.array([5]),
                "junk": np.array([1]),
                "bbx": np.array([1.5, 2.0, 40.0, 30.5]),
            },
            {"easy": np.array([], dtype=np.int64), "hard": [2], "junk": [], "bbx": [np.float64(0.5), 0.0, 10.0, 10.0]},
        ],
    }


@pytest.mark.parametrize("protocol", [2, pickle.HIGHEST_PROTOCOL])
@pytest.mark.parametrize("numpy_module", ["numpy._core.multiarray", "numpy.core.multiarray"])
def test_published_files_with_numpy_arrays_load(tmp_path, protocol, numpy_module):
    content = pickle.dumps(_published_structure(), protocol=protocol)
    if protocol == 2:  # text GLOBAL opcodes: rewrite them as numpy 1.x wrote them
        content = content.replace(b"numpy._core.multiarray", numpy_module.encode())
    path = tmp_path / "gnd_roxford5k.pkl"
    path.write_bytes(content)
    loaded = load_revisited_groundtruth(path)
    assert loaded.qimlist == ["q0", "q1"] and loaded.imlist[7] == "db7"
    np.testing.assert_array_equal(loaded.gnd[0]["bbx"], [1.5, 2.0, 40.0, 30.5])
    positives, junk = loaded.labels("medium")
    assert positives.toarray().nonzero()[1].tolist() == [0, 3, 5, 2]
    assert junk.toarray().nonzero()[1].tolist() == [1]


class _CreatesMarker:
    """Unpickled without restriction, calls ``os.system('touch <marker>')``."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        import os

        return os.system, (f"touch {self.marker}",)


def test_a_pickle_that_would_run_code_is_refused_naming_file_and_global(tmp_path):
    marker = tmp_path / "marker"
    path = tmp_path / "gnd_roxford5k.pkl"
    path.write_bytes(pickle.dumps({**GROUNDTRUTH, "gnd": [_CreatesMarker(marker), GROUNDTRUTH["gnd"][1]]}))
    with pytest.raises(RefusedGlobalError, match=rf"{path}: refused to unpickle the global (posix|os)\.system"):
        load_revisited_groundtruth(path)
    assert not marker.exists()


def test_other_callables_than_numpy_reconstruction_are_refused(tmp_path):
    path = tmp_path / "gnd.pkl"
    path.write_bytes(
        pickle.dumps({"imlist": [], "qimlist": [], "gnd": [], "when": __import__("datetime").date(2020, 1, 1)})
    )
    with pytest.raises(RefusedGlobalError, match=r"gnd\.pkl: refused to unpickle the global datetime\.date"):
        load_revisited_groundtruth(path)


# ----------------------------------------------------- crafted files: never a crash, always the file named


def test_a_crafted_object_dtype_is_refused_instead_of_crashing_the_interpreter(tmp_path):
    path = tmp_path / "gnd_roxford5k.pkl"
    path.write_bytes(pickle.dumps({**GROUNDTRUTH, "gnd": [{"easy": ObjectPointerArray(), "hard": [], "junk": []}] * 2}))
    process = error_in_subprocess("locretrieval.metrics.revisited.load_revisited_groundtruth", path)
    assert process.returncode == 0, process.stderr[-2000:]  # -11 (SIGSEGV) before the stand-ins
    assert process.stdout.startswith(f"{path}: refused dtype 'V8' with fields or a sub-array")


def test_a_size_is_never_allocated_from_a_pickle(tmp_path):
    path = tmp_path / "gnd_roxford5k.pkl"
    # builtins.bytes(1 << 44), as protocol 2 writes a call: 16 TiB asked by a 40-byte file
    path.write_bytes(b"\x80\x02c__builtin__\nbytes\nq\x00\x8a\x06\x00\x00\x00\x00\x00\x10\x85R.")
    with pytest.raises(RefusedPickleError, match=rf"{path}: refused the call bytes\(17592186044416,\)"):
        load_revisited_groundtruth(path)


def test_shared_references_cannot_blow_up_a_small_file(tmp_path):
    row = list(range(1000))
    path = tmp_path / "gnd_roxford5k.pkl"
    path.write_bytes(pickle.dumps({**GROUNDTRUTH, "imlist": [row] * 100_000}))  # 200 kB, 10^8 values shared
    with pytest.raises(RefusedPickleError, match=r"gnd_roxford5k\.pkl: refused a structure of more than \d+ elements"):
        load_revisited_groundtruth(path)


@pytest.mark.parametrize(
    "entry, message",
    [
        ({"easy": ["a"], "hard": [], "junk": []}, r"gnd entry 0 \(q0\) has easy that are not integer indices"),
        ({"easy": [[1], 2], "hard": [], "junk": []}, r"gnd entry 0 \(q0\) has easy that are not integer indices"),
        ({"easy": [10**30], "hard": [], "junk": []}, r"gnd entry 0 \(q0\) has easy that are not integer indices"),
        ([1, 2], r"gnd entry 0 \(q0\) must be a dict with easy, hard and junk, found list"),
    ],
)
def test_a_wrong_structure_names_the_file_and_the_entry(tmp_path, entry, message):
    path = tmp_path / "gnd_roxford5k.pkl"
    path.write_bytes(pickle.dumps({**GROUNDTRUTH, "gnd": [entry, GROUNDTRUTH["gnd"][1]]}))
    with pytest.raises(DataFileError, match=rf"{path}: {message}"):
        load_revisited_groundtruth(path)
