"""How many returns a frame the pose refinement registers: 400 (the default), 800 or 1600.

``RefineConfig.max_points_per_frame`` caps the returns each frame takes part in the registration
with (the normals' neighbourhoods grow with it, ``refine.terms.normal_neighbours``). A car beside
the ego seen from end to end has thousands of returns a frame, and the few at its end faces are
what pin it along the road; more of them should pin it better, at a cost in the refine stage.
Generates small hard-world segments (5 cm / 1 deg label noise, every camera) for several seeds:
box cars on their centres, cars shaped as a body and a cabin, and cabin cars with 2 cm lidar
range noise; annotates each with each cap and scores the tracks against the exact truth with
``bench_visibility``'s clip selection (``bench/refine_worlds.py``). Writes the ``bench_points``
block of docs/benchmarks.md.

    .venv/bin/python bench/bench_points.py                        # seeds 7, 8, ~8 min
    .venv/bin/python bench/bench_points.py --seeds 7 --no-docs     # ~4 min
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DOC_START, DOC_END = "<!-- bench_points:start -->", "<!-- bench_points:end -->"
#: the worlds of one seed (label, SynthConfig options), each with 5 cm / 1 deg labels
WORLDS = (("box cars", {}), ("cabin cars", {"car_shape": "cabin"}),
          ("cabin cars, 2 cm range noise", {"car_shape": "cabin", "range_noise_m": 0.02}))
#: (name, refine options) compared on every world
SETTINGS = (("400 (default)", {}), ("800", {"max_points_per_frame": 800}),
            ("1600", {"max_points_per_frame": 1600}))


def main(argv: list[str] | None = None) -> int:
    from bench.refine_worlds import run

    intro = ("`bench/bench_points.py` (small hard world, {frames} frames, 5 cm / 1 deg labels, seeds {seeds}, each "
             "with box cars, cars shaped as a body and a cabin, and cabin cars with 2 cm lidar range noise; columns: "
             "`RefineConfig.max_points_per_frame`; `bench_visibility`'s clip selection and scoring; "
             "docs/refinement.md, \"Returns per frame\").")
    return run(argv, __doc__.splitlines()[0], "7,8", WORLDS, SETTINGS,
               "Returns a frame the pose refinement registers, on noisy labels", intro, DOC_START, DOC_END)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
