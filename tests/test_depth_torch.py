"""The batched torch nearest-neighbour completer agrees with the CPU one."""
from __future__ import annotations

import math
import sys

import numpy as np
import pytest
from scipy import ndimage

from drivetrack.depth import get_completer

torch = pytest.importorskip("torch")


def random_sparse(rng, shape, density):
    """Sparse maps whose returns all have distinct depths (so a depth identifies its return)."""
    known = rng.random(shape) < density
    sparse = np.zeros(shape, np.float32)
    sparse[known] = rng.permutation(np.arange(1, known.sum() + 1)).astype(np.float32) * 0.01 + 1.0
    return sparse


def distance_to_chosen_return(sparse, dense):
    """Pixel distance from every filled pixel to the return whose depth it took."""
    rows, cols = np.nonzero(sparse)
    order = np.argsort(sparse[rows, cols])
    values = sparse[rows, cols][order]
    filled = dense > 0
    where = np.searchsorted(values, dense[filled])
    assert np.all(values[where] == dense[filled]), "a filled depth is no return's depth"
    pixel_rows, pixel_cols = np.nonzero(filled)
    return np.hypot(rows[order][where] - pixel_rows, cols[order][where] - pixel_cols), filled


@pytest.mark.parametrize("reach", [6.0, math.inf])
def test_torch_matches_exact_nearest_and_cpu(reach):
    rng = np.random.default_rng(3)
    sparse = random_sparse(rng, (2, 96, 128), 0.03)
    torch_dense = get_completer("nearest-torch", max_reach_px=reach, device="cpu")(sparse)
    cpu_dense = get_completer("nearest", max_reach_px=reach)(sparse)
    assert torch_dense.shape == sparse.shape and torch_dense.dtype == np.float32
    assert np.mean(torch_dense == cpu_dense) > 0.95  # ties may differ
    for index in range(sparse.shape[0]):
        exact, _ = ndimage.distance_transform_edt(sparse[index] == 0, return_indices=True)
        expected_filled = exact <= reach
        np.testing.assert_array_equal(torch_dense[index] > 0, expected_filled)
        chosen, filled = distance_to_chosen_return(sparse[index], torch_dense[index])
        np.testing.assert_allclose(chosen, exact[filled], atol=1e-6)  # a nearest return, always
        chosen_cpu, filled_cpu = distance_to_chosen_return(sparse[index], cpu_dense[index])
        excess = chosen_cpu - exact[filled_cpu]
        assert excess.max() < 0.5 and np.mean(excess > 1e-6) < 0.01  # chamfer: nearly exact


def test_torch_tensor_in_tensor_out_and_empty():
    completer = get_completer("nearest-torch", device="cpu", max_reach_px=3)
    assert completer.name == "nearest-torch"
    sparse = torch.zeros(2, 10, 12)
    sparse[0, 5, 5] = 9.0
    dense = completer(sparse)
    assert isinstance(dense, torch.Tensor) and dense.shape == (2, 10, 12)
    assert dense[0, 5, 8] == 9.0 and dense[0, 5, 9] == 0.0 and not dense[1].any()
    single = completer(sparse[0].numpy())
    assert isinstance(single, np.ndarray) and single.shape == (10, 12)
    with pytest.raises(TypeError, match="expected dtype float32, found torch.float64"):
        completer(torch.zeros(3, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="up to 8192 px per side, found 9000x1"):
        completer(np.ones((1, 9000), np.float32))
    with pytest.raises(ValueError, match="bad device 'nonsense'"):
        get_completer("nearest-torch", device="nonsense")


def test_missing_torch_gives_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", None)  # what an environment without torch sees
    with pytest.raises(ImportError, match=r"'nearest-torch' needs PyTorch.*pip install 'drivetrack\[torch\]'"):
        get_completer("nearest-torch")
