"""drivetrack.storage: atomic, deterministic writes through fsspec."""
import hashlib
import os

import numpy as np
import pandas as pd
import pytest

from drivetrack.storage import StreamedArray, atomic_local_path, write_npz


def test_npz_bytes_are_deterministic_and_load_without_pickle(tmp_path):
    arrays = {"tracks": np.arange(12, dtype=np.float32).reshape(2, 3, 2), "visibles": np.ones((2, 3), bool)}
    first = tmp_path / "a" / "clip.npz"
    second = tmp_path / "b" / "clip.npz"
    write_npz(str(first), arrays)
    write_npz(str(second), arrays)
    assert hashlib.sha256(first.read_bytes()).digest() == hashlib.sha256(second.read_bytes()).digest()
    with np.load(first, allow_pickle=False) as z:
        np.testing.assert_array_equal(z["tracks"], arrays["tracks"])


def test_failed_write_leaves_nothing_and_names_the_url(tmp_path):
    target = tmp_path / "out" / "x.bin"
    with pytest.raises(OSError, match="could not write .*x.bin"):
        with atomic_local_path(str(target)) as tmp:
            open(tmp, "wb").write(b"half")
            raise RuntimeError("disk full")
    assert not target.exists() and list((tmp_path / "out").iterdir()) == []


def test_object_arrays_are_refused(tmp_path):
    with pytest.raises(ValueError, match="dtype object"):
        write_npz(str(tmp_path / "x.npz"), {"a": np.array([None])})


def _pieces(array, sizes):
    """Chunks of ``array`` along axis 0 with the given row counts (cycled)."""
    def chunks():
        start, i = 0, 0
        while start < array.shape[0]:
            stop = start + sizes[i % len(sizes)]
            yield array[start:stop]
            start, i = stop, i + 1
    return chunks


@pytest.mark.parametrize("sizes", [[1], [3], [5, 1, 2], [10_000]])
def test_streamed_arrays_give_the_bytes_of_whole_arrays(tmp_path, sizes):
    rng = np.random.default_rng(0)
    arrays = {"video": rng.integers(0, 255, (7, 9, 11, 3), dtype=np.uint8),
              "tracks": rng.normal(size=(13, 7, 2)).astype(np.float32),
              "visibles": rng.random((13, 7)) > 0.5,
              "jpeg": np.array([b"\xff\xd8ab\xff\xd9", b"\xff\xd8abcdef\xff\xd9", b"\xff\xd8\xff\xd9"]),
              "none": np.zeros((0, 7, 3), np.float32)}
    write_npz(str(tmp_path / "whole.npz"), arrays)
    streamed = write_npz(str(tmp_path / "streamed.npz"),
                         {k: StreamedArray(v.shape, v.dtype, _pieces(v, sizes)) if k != "visibles" else v
                          for k, v in arrays.items()})
    assert (tmp_path / "whole.npz").read_bytes() == (tmp_path / "streamed.npz").read_bytes()
    with np.load(streamed, allow_pickle=False) as z:
        for key, value in arrays.items():
            assert z[key].dtype == value.dtype and z[key].shape == value.shape
            np.testing.assert_array_equal(z[key], value)


@pytest.mark.parametrize("bad, message", [
    (lambda: iter([np.zeros((2, 4), np.float32), np.zeros((1, 5), np.float32)]),
     r"but chunk 1 \(after 2 rows\) is float32 \(1, 5\)"),
    (lambda: iter([np.zeros((3, 4), np.float64)]), r"chunk 0 \(after 0 rows\) is float64"),
    (lambda: iter([np.zeros((2, 4), np.float32)]), r"its chunks gave 2 rows"),
    (lambda: iter([np.zeros((2, 4), np.float32), np.zeros((2, 4), np.float32)]), r"chunk 1 \(after 2 rows\)"),
    (lambda: iter([[1.0, 2.0, 3.0, 4.0]]), r"chunk 0 \(after 0 rows\) is list"),
])
def test_wrong_chunks_raise_naming_url_and_key_and_leave_no_file(tmp_path, bad, message):
    target = tmp_path / "out" / "clip.npz"
    with pytest.raises(ValueError, match=r"clip\.npz: array 'tracks' is declared float32 \(3, 4\), .*" + message):
        write_npz(str(target), {"ok": np.arange(3), "tracks": StreamedArray((3, 4), np.float32, bad)})
    assert not target.exists() and list((tmp_path / "out").iterdir()) == []


def test_streamed_array_needs_a_dimension_and_no_objects(tmp_path):
    with pytest.raises(ValueError, match="at least one dimension"):
        StreamedArray((), np.float32, lambda: iter(()))
    with pytest.raises(ValueError, match="dtype object"):
        write_npz(str(tmp_path / "x.npz"), {"a": StreamedArray((1,), object, lambda: iter(()))})


def test_side_writers_are_atomic_create_parents_and_round_trip(tmp_path):
    import pandas as pd
    import pyarrow as pa

    from drivetrack.storage import read_json, write_bytes, write_json, write_parquet

    base = tmp_path / "deep" / "er"
    assert write_bytes(str(base / "a.bin"), b"\x00abc") == str(base / "a.bin")
    assert (base / "a.bin").read_bytes() == b"\x00abc"
    write_json(str(base / "r.json"), {"b": 1, "a": [1.5]}, indent=2, sort_keys=True)
    assert (base / "r.json").read_text() == '{\n  "a": [\n    1.5\n  ],\n  "b": 1\n}'
    assert read_json(str(base / "r.json")) == {"a": [1.5], "b": 1}
    frame = pd.DataFrame({"x": [1, 2], "y": ["p", "q"]})
    write_parquet(str(base / "t.parquet"), frame)
    pd.testing.assert_frame_equal(pd.read_parquet(base / "t.parquet"), frame)
    write_parquet(str(base / "u.parquet"), pa.table({"x": [3]}))
    assert pd.read_parquet(base / "u.parquet")["x"].tolist() == [3]
    assert sorted(p.name for p in base.iterdir()) == ["a.bin", "r.json", "t.parquet", "u.parquet"]


def test_a_value_json_cannot_hold_writes_nothing_and_names_the_file(tmp_path):
    from drivetrack.storage import write_json

    target = tmp_path / "out" / "run.json"
    target.parent.mkdir()
    target.write_text('{"old": true}')
    with pytest.raises(ValueError, match="run.json"):
        write_json(str(target), {"bad": object()})
    with pytest.raises(ValueError, match="run.json"):
        write_json(str(target), {"nan": float("nan")} | {"x": {1, 2}})
    assert target.read_text() == '{"old": true}' and len(list(target.parent.iterdir())) == 1


def test_a_corrupt_json_record_is_an_error_naming_the_file_not_none(tmp_path):
    from drivetrack.storage import read_json

    for name, data in (("cut.json", b'{"status": "do'), ("bin.json", b"\xff\xfe\x00"), ("empty.json", b"")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(ValueError, match=name):
            read_json(str(tmp_path / name))
    assert read_json(str(tmp_path / "missing.json"), missing_ok=True) is None
    with pytest.raises(FileNotFoundError, match="missing.json"):
        read_json(str(tmp_path / "missing.json"))


def test_atomic_writes_get_the_umask_mode_not_mkstemp_0600(tmp_path):
    """Files written atomically are readable as ``open`` would make them (0o666 minus the umask),
    not mkstemp's owner-only 0600: a web server or another user publishing the folder reads them."""
    import stat

    from drivetrack.storage import FILE_MODE, write_bytes, write_json, write_parquet

    mask = os.umask(0o022)
    os.umask(mask)
    assert FILE_MODE == 0o666 & ~mask
    written = [write_bytes(str(tmp_path / "a.bin"), b"x"), write_json(str(tmp_path / "b.json"), {"a": 1}),
               write_parquet(str(tmp_path / "c.parquet"), pd.DataFrame({"a": [1]}))]
    for path in written:
        assert stat.S_IMODE(os.stat(path).st_mode) == FILE_MODE, path
    # and a file written by plain open() in the same folder has the same bits
    (tmp_path / "d").write_bytes(b"x")
    assert stat.S_IMODE(os.stat(tmp_path / "d").st_mode) == FILE_MODE
