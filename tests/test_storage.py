"""drivetrack.storage: atomic, deterministic writes through fsspec."""
import hashlib

import numpy as np
import pytest

from drivetrack.storage import atomic_local_path, write_npz


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
