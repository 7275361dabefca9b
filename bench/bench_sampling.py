"""Which returns of each frame the pose refinement registers: uniform, normal-space (the default) or 10 cm cubes.

The refinement takes at most ``RefineConfig.max_points_per_frame`` returns a frame. Generates
small hard-world segments (5 cm / 1 deg label noise, every camera) for several seeds: movers on
their box centres, on their rear axles (``rear_axle_fraction`` 0.3), and cars shaped as a body
and a cabin; annotates each with the subset drawn uniformly (``sample_normals=False``), shared
among the directions the returns' surfaces face (``sample_normals``, the default) and spread over
10 cm cubes (``sample_voxel_m`` 0.1), and scores the tracks against the exact truth with
``bench_visibility``'s clip selection (``bench/refine_worlds.py``). Writes the ``bench_sampling``
block of docs/benchmarks.md.

    .venv/bin/python bench/bench_sampling.py                        # seeds 7-10, ~7 min
    .venv/bin/python bench/bench_sampling.py --seeds 7 --no-docs     # ~2 min
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DOC_START, DOC_END = "<!-- bench_sampling:start -->", "<!-- bench_sampling:end -->"
#: (name, refine options) compared on every world
SETTINGS = (("uniform", {"sample_normals": False}), ("normal-space (default)", {}),
            ("10 cm cubes", {"sample_voxel_m": 0.1}))


def main(argv: list[str] | None = None) -> int:
    from bench.refine_worlds import BOX_WORLDS, CABIN_WORLDS, run

    intro = ("`bench/bench_sampling.py` (small hard world, {frames} frames, 5 cm / 1 deg labels, seeds {seeds}, each "
             "with box cars driving on their centres, on their rear axles (`rear_axle_fraction` 0.3), and cars shaped "
             "as a body and a cabin; `bench_visibility`'s clip selection and scoring; docs/refinement.md, "
             "\"Normal-space sampling\").")
    return run(argv, __doc__.splitlines()[0], "7,8,9,10", BOX_WORLDS + CABIN_WORLDS, SETTINGS,
               "Which returns the pose refinement registers, on noisy labels", intro, DOC_START, DOC_END)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
