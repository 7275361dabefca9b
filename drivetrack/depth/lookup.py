"""Sub-pixel depth look-up: the maximum over the (up to) four surrounding pixels."""
from __future__ import annotations

import numpy as np

__all__ = ["lookup_max4"]


def lookup_max4(depth: np.ndarray, pixels: np.ndarray, grow_px: int = 0) -> np.ndarray:
    """Depth at sub-pixel positions, the maximum over the pixels whose centres surround them.

    DriveTrack's choice (paper section 3.4): max pooling over the four corner pixels of the
    bilinear neighbourhood over-estimates depth slightly but gives more accurate occlusion.

    Pixel ``i`` covers ``[i, i + 1)``, so its centre is ``i + 0.5``. A position (x, y) takes the
    columns ``floor(x - 0.5)`` and ``ceil(x - 0.5)`` and the rows ``floor(y - 0.5)`` and
    ``ceil(y - 0.5)``: the pixels a bilinear interpolation would weight non-zero. Exactly on a
    pixel centre that is the pixel alone; on the line between two centres, those two.

    Args:
        depth: float32 [H, W] (one map) or [B, H, W] (a batch), metres, ``0`` = unknown.
        pixels: float [..., 2] pixel (x, y). For a batch of maps, the leading dimension of
            ``pixels`` is the batch: [B, ..., 2] (position ``pixels[b]`` reads ``depth[b]``).
        grow_px: also every pixel within ``grow_px`` (rows and columns) of those (0: the four
            alone). The track stage's surface test grows it where the labels jitter
            (``TrackConfig.depth_lookup_px``): an outline the completion spread past by a pixel
            or two no longer hides what lies beside it.
    Returns:
        float32 [...] (``pixels.shape[:-1]``), metres. ``0`` (unknown) for positions outside
        ``[0, W) x [0, H)``, NaN positions, or where every surrounding pixel is unknown.
        Neighbours outside the image count as unknown; an unknown neighbour (0) never wins over
        a known one (depths are positive).
    """
    depth = np.asarray(depth)
    pixels = np.asarray(pixels)
    if depth.ndim not in (2, 3):
        raise ValueError(f"depth: expected float32 [H, W] or [B, H, W], found shape {depth.shape}")
    if not np.issubdtype(depth.dtype, np.floating):
        raise TypeError(f"depth: expected float32, found {depth.dtype}")
    if pixels.ndim < 1 or pixels.shape[-1] != 2:
        raise ValueError(f"pixels: expected float [..., 2] (x, y), found shape {pixels.shape}")
    if depth.ndim == 3 and (pixels.ndim < 2 or pixels.shape[0] != depth.shape[0]):
        raise ValueError(f"pixels: with a batch of {depth.shape[0]} depth maps expected shape "
                         f"[{depth.shape[0]}, ..., 2], found {pixels.shape}")
    height, width = depth.shape[-2:]
    x = pixels[..., 0].astype(np.float64)
    y = pixels[..., 1].astype(np.float64)
    with np.errstate(invalid="ignore"):
        inside = (x >= 0) & (x < width) & (y >= 0) & (y < height)  # False for NaN
    x = np.where(inside, x, 0.5) - 0.5
    y = np.where(inside, y, 0.5) - 0.5
    flat = depth.reshape(-1) if depth.ndim == 2 else depth.reshape(depth.shape[0], -1)
    if depth.ndim == 3:
        batch_offset = (np.arange(depth.shape[0]) * (height * width)).reshape(
            (-1,) + (1,) * (pixels.ndim - 2))
        flat = flat.reshape(-1)
    else:
        batch_offset = 0
    if grow_px < 0:
        raise ValueError(f"grow_px: expected an integer >= 0, found {grow_px}")
    best = np.zeros(x.shape, dtype=np.float32)
    # floor - grow .. floor and ceil .. ceil + grow (a pixel twice on a centre: the same maximum)
    cols = [np.floor(x) - d for d in range(grow_px + 1)] + [np.ceil(x) + d for d in range(grow_px + 1)]
    rows = [np.floor(y) - d for d in range(grow_px + 1)] + [np.ceil(y) + d for d in range(grow_px + 1)]
    for col in cols:
        col_ok = (col >= 0) & (col < width)
        for row in rows:
            ok = col_ok & (row >= 0) & (row < height) & inside
            index = (np.where(ok, row, 0) * width + np.where(ok, col, 0)).astype(np.int64)
            values = flat[index + batch_offset]
            np.maximum(best, np.where(ok, values, 0).astype(np.float32), out=best)
    return best
