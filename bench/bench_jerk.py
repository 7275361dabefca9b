"""The refinement's jerk stiffness chosen from each object's labels (``RefineConfig.jerk_sigma_choices_mps3``) against the fixed 5 m/s^3 of before.

Generates small hard-world segments (``SynthConfig(world="hard")``, 5 cm / 1 deg label noise,
every camera) for several seeds, each with box cars (on their box centres and on their rear axles),
cars shaped as a body and a cabin (with and without 2 cm of lidar range noise), and box and cabin
cars whose movers speed up and brake (``speed_changes_mps2`` 2: where a stiff jerk term would
smooth the change away); annotates each with the fixed stiffness and the chosen one, and scores the
tracks against the exact truth with ``bench_visibility``'s clip selection (five cameras, every
object type, ``min_frames`` 8, ``max_camera_distance_m`` 75): clip AJ weighted by tracks, mean and
lowest clip AJ, wrong occlusion calls, pixel error of the truly visible point-frames
(``bench/refine_worlds.py``). Writes the ``bench_jerk`` block of docs/benchmarks.md.

    .venv/bin/python bench/bench_jerk.py                          # seeds 7-10, ~25 min
    .venv/bin/python bench/bench_jerk.py --seeds 7 --no-docs       # ~6 min
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DOC_START, DOC_END = "<!-- bench_jerk:start -->", "<!-- bench_jerk:end -->"
#: (name, refine options) compared on every world
SETTINGS = (("fixed 5 m/s^3 (before)", {"jerk_sigma_choices_mps3": []}), ("chosen from the labels (default)", {}))
#: movers that speed up and brake (the case a stiff jerk term gets wrong)
SPEED_CHANGE_WORLDS = (("box cars, speed changes", {"speed_changes_mps2": 2.0}),
                       ("cabin cars, speed changes, 2 cm range noise",
                        {"car_shape": "cabin", "speed_changes_mps2": 2.0, "range_noise_m": 0.02}))


def main(argv: list[str] | None = None) -> int:
    from bench.refine_worlds import BOX_WORLDS, CABIN_WORLDS, run

    worlds = BOX_WORLDS + CABIN_WORLDS + (("cabin cars, 2 cm range noise", {"car_shape": "cabin", "range_noise_m": 0.02}),) \
        + SPEED_CHANGE_WORLDS
    intro = ("`bench/bench_jerk.py` (small hard world, {frames} frames, 5 cm / 1 deg labels, seeds {seeds}, each with "
             "box cars on their centres and on their rear axles, cabin cars with and without 2 cm range noise, and "
             "movers that speed up and brake (`speed_changes_mps2` 2) as box and as cabin cars; `bench_visibility`'s "
             "clip selection and scoring; other refinement settings at their defaults; docs/refinement.md, "
             "\"The jerk term's stiffness from the labels\").")
    return run(argv, __doc__.splitlines()[0], "7,8,9,10", worlds, SETTINGS,
               "The refinement's jerk stiffness chosen from the labels", intro, DOC_START, DOC_END)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
