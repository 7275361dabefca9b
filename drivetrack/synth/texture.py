"""Procedural textures: hashed value noise, the road surface and object faces.

Pure functions of surface coordinates (metres), so a surface point has the same colour in every
frame and every camera: the textures are what point trackers lock onto.
"""
from __future__ import annotations

import numpy as np

from drivetrack.synth.world import CURB_Y, FAR_CURB_Y, LANE_WIDTH

__all__ = ["value_noise", "ground_albedo", "face_albedo", "SKY_TOP", "SKY_HORIZON"]

SKY_TOP = np.array([0.35, 0.55, 0.85], dtype=np.float32)
SKY_HORIZON = np.array([0.80, 0.86, 0.92], dtype=np.float32)


_TABLE_SIZE = 256
_TABLES: dict[int, np.ndarray] = {}


def _table(seed: int) -> np.ndarray:
    """float32 [256 * 256] random lattice values of one noise seed (cached, deterministic)."""
    table = _TABLES.get(seed)
    if table is None:
        table = np.random.default_rng(seed).random(_TABLE_SIZE * _TABLE_SIZE, dtype=np.float32)
        if len(_TABLES) > 64:
            _TABLES.clear()
        _TABLES[seed] = table
    return table


def value_noise(x: np.ndarray, y: np.ndarray, scale: float, seed: int) -> np.ndarray:
    """Smooth value noise float32 [...] in [0, 1] at (x, y) metres, lattice spacing ``scale``.

    Lattice values come from a 256 x 256 table per seed (the pattern repeats every 256 cells,
    i.e. every 90 m and more: far beyond what a segment sees of one surface).
    """
    table = _table(seed)
    x, y = np.asarray(x), np.asarray(y)
    inv = np.asarray(1.0 / scale, dtype=np.result_type(x.dtype, np.float32))
    gx, gy = x * inv, y * inv
    fx, fy = np.floor(gx), np.floor(gy)
    tx, ty = (gx - fx).astype(np.float32), (gy - fy).astype(np.float32)
    ix = fx.astype(np.int64) & (_TABLE_SIZE - 1)
    iy = fy.astype(np.int64) & (_TABLE_SIZE - 1)
    ix1, iy1 = (ix + 1) & (_TABLE_SIZE - 1), (iy + 1) & (_TABLE_SIZE - 1)
    tx, ty = tx * tx * (3 - 2 * tx), ty * ty * (3 - 2 * ty)
    row0, row1 = iy * _TABLE_SIZE, iy1 * _TABLE_SIZE
    a, b = table[row0 + ix], table[row0 + ix1]
    c, d = table[row1 + ix], table[row1 + ix1]
    top = a + (b - a) * tx
    return top + ((c + (d - c) * tx) - top) * ty


def ground_albedo(x: np.ndarray, y: np.ndarray, seed: int) -> np.ndarray:
    """float32 [..., 3] RGB albedo of the ground at world (x, y) metres.

    Asphalt between the curbs (checker 2 m + two octaves of noise + dashed white lane lines at
    y = -3.5, -7 and +3.5 m, a solid white line at y = -10.5 m between the outer lane and the
    parking strip, and a solid yellow centre line at y = 0), a white curb, light paving tiles
    beyond the curbs.
    """
    n1 = value_noise(x, y, 0.35, seed)
    n2 = value_noise(x, y, 2.7, seed + 1)
    checker = ((np.floor(x * 0.5) + np.floor(y * 0.5)) % 2).astype(np.float32)
    asphalt = 0.22 + 0.05 * checker + 0.10 * n1 + 0.08 * n2
    tiles = ((np.floor(x / 0.6) + np.floor(y / 0.6)) % 2).astype(np.float32)
    paving = 0.5 + 0.06 * tiles + 0.15 * n1
    road = (y > CURB_Y) & (y < FAR_CURB_Y)
    lane = np.round(y / LANE_WIDTH)
    white = ((np.abs(y - lane * LANE_WIDTH) < 0.08) & ((lane == -1) | (lane == -2) | (lane == 1))
             & (np.mod(x, 9.0) < 4.5))
    white |= np.abs(y - CURB_Y) < 0.15
    white |= np.abs(y + 3 * LANE_WIDTH) < 0.08                           # the parking strip's edge
    gray = np.where(road, asphalt, paving)
    gray = np.where(white, np.float32(0.85), gray)
    tint_g = np.where(road, np.float32(1.0), np.float32(0.9))
    tint_b = np.where(road, np.float32(1.0), np.float32(0.82))
    centre = np.abs(y) < 0.1
    rgb = np.stack([np.where(centre, np.float32(0.85), gray * np.where(road, np.float32(1.0), np.float32(0.95))),
                    np.where(centre, np.float32(0.70), gray * tint_g),
                    np.where(centre, np.float32(0.15), gray * tint_b)], axis=-1)
    return rgb.astype(np.float32, copy=False)


def face_albedo(coord_a: np.ndarray, coord_b: np.ndarray, color: np.ndarray, pattern: int,
                scale: float, seed: int) -> np.ndarray:
    """float32 [N, 3] RGB albedo of box-face points with in-face coordinates (metres)."""
    n = value_noise(coord_a, coord_b, scale * 0.7, seed)
    if pattern == 0:
        cell = ((np.floor(coord_a / scale) + np.floor(coord_b / scale)) % 2).astype(np.float32)
    else:
        cell = (np.floor(coord_b / scale) % 2).astype(np.float32)
    shade = 0.55 + 0.3 * cell + 0.3 * n
    return np.clip(shade[:, None] * np.asarray(color, dtype=np.float32)[None, :], 0.0, 1.0)
