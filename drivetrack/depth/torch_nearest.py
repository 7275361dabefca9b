"""Batched nearest-neighbour completion in torch (jump flooding), for GPU workers.

Jump flooding (Rong and Tan, 2006) propagates, for every pixel, the coordinates of the nearest
seed found so far: at step ``k`` each pixel looks at the seeds held by the 8 pixels ``k`` away
and keeps the nearest. With reach ``R``, starting at the power of two ``k >= (R + 1) / 2`` and
halving to 1 lets a seed reach every pixel within ``R`` (each offset up to ``2k - 1`` is a sum of
steps); a final extra pass at step 1 (JFA+1) corrects most of the rare misses. Cost: ``9 (log2 k + 2)``
element-wise passes over the batch, no per-pixel Python.
"""
from __future__ import annotations

import math

from drivetrack.depth.completers import (DepthCompleter, _check_reach, check_sparse,
                                         default_max_reach_px)

__all__ = ["TorchNearestCompleter", "import_torch"]

_FAR = -(1 << 14)  # coordinate of "no seed yet": farther than any real seed for images < 8k px


def import_torch():
    """Import torch or say how to install it."""
    try:
        import torch
    except ImportError as error:
        raise ImportError(
            "depth completer 'nearest-torch' needs PyTorch, which is not installed: "
            "pip install 'drivetrack[torch]' (or a CUDA build of torch on a GPU node), "
            "or use the CPU completer 'nearest'") from error
    return torch


def nearest_seed_jfa(known, reach: float):
    """Jump flooding: nearest seed coordinates per pixel.

    Args:
        known: bool tensor [B, H, W], the seeds.
        reach: only seeds within this pixel distance matter (``inf``: any).
    Returns:
        ``(seed_y, seed_x, distance_sq)``: int32 [B, H, W] coordinates of the nearest seed found
        (``_FAR`` where none) and int32 squared distance.
    """
    torch = import_torch()
    batch, height, width = known.shape
    if max(height, width) > 8192:  # int32 squared distances to _FAR must not overflow
        raise ValueError(f"completer 'nearest-torch': images up to 8192 px per side, found "
                         f"{width}x{height}")
    device = known.device
    rows = torch.arange(height, device=device, dtype=torch.int32).view(1, height, 1)
    cols = torch.arange(width, device=device, dtype=torch.int32).view(1, 1, width)
    far = torch.tensor(_FAR, device=device, dtype=torch.int32)
    seed_y = torch.where(known, rows.expand(batch, height, width), far)
    seed_x = torch.where(known, cols.expand(batch, height, width), far)
    best = (seed_y - rows) ** 2 + (seed_x - cols) ** 2
    limit = max(height, width) if not math.isfinite(reach) else min(reach, max(height, width))
    # steps k, k/2, ..., 1 reach every offset up to 2k - 1: start at the power of two k >= (R + 1) / 2
    step = 1 << max(int(math.ceil(math.log2(max((limit + 1) / 2, 1.0)))), 0)
    steps = []
    while step >= 1:
        steps.append(step)
        step //= 2
    steps.append(1)  # JFA+1
    for step in steps:
        # pad once per step; every candidate is then a view, no copy
        pad = (step, step, step, step)
        padded_y = torch.nn.functional.pad(seed_y, pad, value=_FAR)
        padded_x = torch.nn.functional.pad(seed_x, pad, value=_FAR)
        for dy in (-step, 0, step):
            for dx in (-step, 0, step):
                if dy == 0 and dx == 0:
                    continue
                cand_y = padded_y[:, step + dy:step + dy + height, step + dx:step + dx + width]
                cand_x = padded_x[:, step + dy:step + dy + height, step + dx:step + dx + width]
                dist = cand_y - rows
                dist.mul_(dist)
                step_x = cand_x - cols
                dist.addcmul_(step_x, step_x)
                better = dist < best
                best = torch.where(better, dist, best)
                seed_y = torch.where(better, cand_y, seed_y)
                seed_x = torch.where(better, cand_x, seed_x)
    return seed_y, seed_x, best


class TorchNearestCompleter(DepthCompleter):
    """The ``nearest`` completer for a batch at once in torch (CUDA when available, else CPU).

    Same result as :class:`~drivetrack.depth.completers.NearestCompleter` except on ties and on
    the rare pixels where either algorithm misses the exact nearest (see docs/depth.md).

    Args:
        max_reach_px: as for ``nearest`` (``None`` = 20 px * width / 1920, ``inf`` = no limit).
        device: torch device, e.g. ``"cuda:1"``; ``None`` picks ``cuda`` when available.
    Call with a numpy float32 [H, W] / [B, H, W] array (returns numpy) or with a torch float32
    tensor (returns a tensor on the completer's device).
    """
    name = "nearest-torch"

    def __init__(self, max_reach_px: float | None = None, device=None):
        torch = import_torch()
        self.max_reach_px = _check_reach(max_reach_px)
        if device is None:
            device = "cuda" if torch.cuda.is_available() else "cpu"
        try:
            self.device = torch.device(device)
        except (RuntimeError, TypeError) as error:
            raise ValueError(f"completer 'nearest-torch': bad device {device!r}: {error}") from error

    def __call__(self, sparse):
        torch = import_torch()
        if isinstance(sparse, torch.Tensor):
            if sparse.dim() not in (2, 3) or 0 in sparse.shape[-2:]:
                raise ValueError(f"completer {self.name!r}: expected float32 [H, W] or [B, H, W] "
                                 f"with H, W > 0, found shape {tuple(sparse.shape)}")
            if sparse.dtype != torch.float32:
                raise TypeError(f"completer {self.name!r}: expected dtype float32, found {sparse.dtype}")
            tensor = sparse.to(self.device)
            if not bool((torch.isfinite(tensor) & (tensor >= 0)).all()):
                raise ValueError(f"completer {self.name!r}: expected finite depths >= 0 (0 = unknown)")
            return self.complete_tensor(tensor)
        sparse = check_sparse(sparse, self.name)
        with torch.no_grad():
            dense = self.complete_tensor(torch.from_numpy(sparse).to(self.device))
        return dense.cpu().numpy()

    def complete_tensor(self, sparse):
        """float32 tensor [H, W] or [B, H, W] -> the same, on ``self.device``."""
        torch = import_torch()
        single = sparse.dim() == 2
        batch = sparse[None] if single else sparse
        _, height, width = batch.shape
        reach = self.reach_for(width)
        known = batch > 0
        out = torch.zeros_like(batch)
        rows = torch.nonzero(known.any(dim=2).any(dim=0)).flatten()
        if rows.numel() == 0:
            return out[0] if single else out
        # only rows within reach of some return can be filled (like the CPU completer's band)
        pad = int(math.floor(reach)) if math.isfinite(reach) else height
        top = max(int(rows[0]) - pad, 0)
        bottom = min(int(rows[-1]) + pad + 1, height)
        band = batch[:, top:bottom]
        seed_y, seed_x, distance_sq = nearest_seed_jfa(known[:, top:bottom], reach)
        found = seed_y >= 0
        if math.isfinite(reach):
            found &= distance_sq.to(torch.float64) <= reach * reach
        index = (seed_y.clamp(min=0).long() * width + seed_x.clamp(min=0).long()).view(band.shape[0], -1)
        dense = torch.gather(band.reshape(band.shape[0], -1), 1, index).view(band.shape)
        out[:, top:bottom] = torch.where(found, dense, torch.zeros((), dtype=dense.dtype,
                                                                    device=dense.device))
        return out[0] if single else out

    def __repr__(self) -> str:
        return f"TorchNearestCompleter(max_reach_px={self.max_reach_px!r}, device={str(self.device)!r})"
