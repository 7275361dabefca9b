"""Ground-truth look-up: the exact truth of a synthetic segment, indexed by LiDAR return.

A track names the LiDAR return that produced it (clip frame + ``lidar_sources`` = (laser, return,
row, col)); :class:`TruthIndex` turns the clip frame into a segment frame (on
``timestamps_micros``) and finds that return among the truth's ``lidar_hits``.
"""
from __future__ import annotations

import numpy as np

from drivetrack.waymo.lidar import return_keys

__all__ = ["TruthIndex"]

class TruthIndex:
    """The exact truth of one synthetic segment, indexed for matching tracks to LiDAR hits.

    Attributes:
        truth: the :class:`drivetrack.synth.GroundTruth`.
        timestamps_micros: int64 [T_seg].
        object_ids: str [K].
    """

    def __init__(self, truth):
        self.truth = truth
        hits = truth.hits
        self.timestamps_micros = np.asarray(truth.objects["timestamps_micros"], dtype=np.int64)
        self.object_ids = np.asarray(truth.objects["object_id"]).astype(str)
        keys = return_keys(hits["frame"], hits["laser"], hits["return_index"], hits["row"], hits["col"],
                            f"ground truth {truth.url}")
        self._order = np.argsort(keys, kind="stable")
        self._sorted = keys[self._order]
        self._object_index = np.asarray(hits["object_index"], dtype=np.int64)
        self._frame = np.asarray(hits["frame"], dtype=np.int64)

    @classmethod
    def load(cls, root: str, split: str, segment: str) -> "TruthIndex":
        from drivetrack.synth import load_ground_truth
        from drivetrack.synth.ground_truth import ground_truth_url

        try:
            truth = load_ground_truth(root, split, segment)
        except FileNotFoundError as error:
            raise FileNotFoundError(f"segment {segment!r} (split {split!r}) has no synthetic ground truth under "
                                    f"{ground_truth_url(root, split, segment)} ({error}); is the truth root the "
                                    f"synthetic source these annotations were made from?") from None
        return cls(truth)

    def segment_frames(self, timestamps_micros: np.ndarray, where: str) -> np.ndarray:
        """int64 [T]: segment frame of each clip timestamp; raises if one is not a truth frame."""
        ts = np.asarray(timestamps_micros, dtype=np.int64)
        pos = np.clip(np.searchsorted(self.timestamps_micros, ts), 0, max(self.timestamps_micros.size - 1, 0))
        bad = np.flatnonzero(self.timestamps_micros[pos] != ts) if self.timestamps_micros.size else np.arange(ts.size)
        if bad.size:
            raise ValueError(f"{where}: timestamp {int(ts[bad[0]])} (clip frame {int(bad[0])}) is not a frame of "
                             f"ground-truth segment {self.truth.segment!r} ({self.timestamps_micros.size} frames, "
                             f"{int(self.timestamps_micros[0]) if self.timestamps_micros.size else '-'}.."
                             f"{int(self.timestamps_micros[-1]) if self.timestamps_micros.size else '-'}); "
                             f"annotation and truth come from different segments or runs")
        return pos.astype(np.int64)

    def match(self, frame: np.ndarray, lidar_sources: np.ndarray, where: str) -> np.ndarray:
        """int64 [N]: truth hit of each (segment frame [N], (laser, return, row, col) [N, 4]), -1 if none."""
        sources = np.asarray(lidar_sources, dtype=np.int64).reshape(-1, 4)
        keys = return_keys(frame, sources[:, 0], sources[:, 1], sources[:, 2], sources[:, 3], where)
        pos = np.searchsorted(self._sorted, keys)
        pos_clipped = np.minimum(pos, max(self._sorted.size - 1, 0))
        found = (pos < self._sorted.size) & (self._sorted[pos_clipped] == keys) if self._sorted.size \
            else np.zeros(keys.size, bool)
        return np.where(found, self._order[pos_clipped] if self._sorted.size else -1, -1).astype(np.int64)

    def object_index(self, object_id: str, where: str) -> int:
        found = np.flatnonzero(self.object_ids == object_id)
        if found.size == 0:
            raise ValueError(f"{where}: object {object_id!r} is not an object of ground-truth segment "
                             f"{self.truth.segment!r} ({self.object_ids.size} objects)")
        return int(found[0])

    def object_hits(self, object_index: int, frames: np.ndarray) -> np.ndarray:
        """int64 [H]: truth hits of object ``object_index`` at segment frames ``frames``."""
        return np.flatnonzero((self._object_index == object_index) & np.isin(self._frame, frames))

