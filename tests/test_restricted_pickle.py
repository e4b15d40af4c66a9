"""`load_plain_pickle`: plain data loads as ``pickle.load`` gives it, in every protocol; numpy's
reconstructors are checked stand-ins; nothing else, nothing self-referencing, nothing huge."""

import pickle

import numpy as np
import pytest

from locretrieval.restricted_pickle import RefusedPickleError, load_plain_pickle

PLAIN = {
    "big_endian": np.arange(6, dtype=">i4").reshape(2, 3),
    "fortran": np.asfortranarray(np.arange(6.0).reshape(2, 3)),
    "bool": np.array([True, False]),
    "complex": np.array([1 + 2j], dtype=np.complex64),
    "empty": np.zeros((0, 4), dtype=np.uint16),
    "scalars": [np.float32(2.5), np.bool_(True), np.int64(-3), np.uint8(200)],
    "dtype": np.dtype("f2"),
    "python": [{1, 2}, frozenset([3]), b"xy", bytearray(b"q"), 1 + 2j, (1, "x"), 10**30, None, 1.5, "é"],
}


@pytest.mark.parametrize("protocol", range(pickle.HIGHEST_PROTOCOL + 1))
def test_plain_data_loads_as_pickle_loads_it(tmp_path, protocol):
    path = tmp_path / "plain.pkl"
    path.write_bytes(pickle.dumps(PLAIN, protocol=protocol))
    loaded, expected = load_plain_pickle(path), pickle.loads(path.read_bytes())
    for key in ("big_endian", "fortran", "bool", "complex", "empty"):
        assert type(loaded[key]) is np.ndarray and loaded[key].dtype == expected[key].dtype
        assert loaded[key].flags.f_contiguous == expected[key].flags.f_contiguous
        np.testing.assert_array_equal(loaded[key], expected[key])
    assert [(type(v), v) for v in loaded["scalars"]] == [(type(v), v) for v in expected["scalars"]]
    assert loaded["dtype"] == np.dtype("f2")
    assert [(type(v), v) for v in loaded["python"]] == [(type(v), v) for v in expected["python"]]


@pytest.mark.parametrize(
    "value, refused",
    [
        (np.array([object()], dtype=object)[:0], "dtype 'O8'"),
        (np.zeros(2, dtype=[("x", "f4"), ("y", "i4")]), "dtype 'V8' with fields"),
        (np.zeros(2, dtype="V4"), "dtype 'V4' \\(only booleans"),
        (np.zeros(2, dtype="M8[s]"), "dtype 'M8' \\(only booleans"),
        (np.zeros(2, dtype="U3"), "dtype 'U3' \\(only booleans"),
        (np.float64(1.0).astype("m8[s]"), "dtype 'm8' \\(only booleans"),
    ],
)
def test_arrays_that_are_not_numbers_are_refused(tmp_path, value, refused):
    path = tmp_path / "data.pkl"
    path.write_bytes(pickle.dumps({"value": value}))
    with pytest.raises(RefusedPickleError, match=rf"{path}: refused {refused}"):
        load_plain_pickle(path)


def test_a_structure_that_contains_itself_is_refused(tmp_path):
    loop = [1]
    loop.append(loop)
    path = tmp_path / "loop.pkl"
    path.write_bytes(pickle.dumps(loop))
    with pytest.raises(RefusedPickleError, match=r"loop\.pkl: refused a structure that contains itself"):
        load_plain_pickle(path)


def test_deep_nesting_is_refused(tmp_path):
    nested = []
    for _ in range(200):
        nested = [nested]
    path = tmp_path / "deep.pkl"
    path.write_bytes(pickle.dumps(nested))
    with pytest.raises(RefusedPickleError, match=r"deep\.pkl: refused containers nested deeper than 64"):
        load_plain_pickle(path)


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", r"not a readable pickle \(pickle exhausted before seeing STOP"),
        (pickle.dumps(list(range(100)))[:-20], r"not a readable pickle \(pickle exhausted before seeing STOP"),
        (b"\x80\x02h\x05.", r"not a readable pickle \(memo entry 5 was never stored"),
        (b"\x80\x02a.", r"not a readable pickle \(an opcode takes a value or mark the stack lacks"),
        (b"\x80\x02cnumpy\nndarray\n(K\x05tR.", r"refused a call of numpy\.ndarray"),
        (b"\x80\x02c_codecs\nencode\nX\x01\x00\x00\x00xX\x04\x00\x00\x00zlib\x86R.", r"refused _codecs\.encode"),
    ],
)
def test_damaged_or_crafted_streams_name_the_file(tmp_path, content, message):
    path = tmp_path / "data.pkl"
    path.write_bytes(content)
    with pytest.raises(RefusedPickleError, match=rf"{path}: {message}"):
        load_plain_pickle(path)
