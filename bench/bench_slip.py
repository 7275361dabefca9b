"""The refinement's no-side-slip prior (``RefineConfig.slip_sigma_mps``) on noisy labels, before and after.

Generates small hard-world segments (``SynthConfig(world="hard")``, 5 cm / 1 deg label noise,
every camera) for several seeds, each with movers driving on their box centres and on their rear
axles (``rear_axle_fraction`` 0.3: a centre slips sideways on a turn, as a real car's does),
annotates each with the prior off and at the default, and scores the tracks against the exact
truth with ``bench_visibility``'s clip selection (five cameras, every object type, ``min_frames``
8, ``max_camera_distance_m`` 75): clip AJ weighted by tracks, mean and lowest clip AJ, wrong
occlusion calls, pixel error of the truly visible point-frames (``bench/refine_worlds.py``).
Writes the ``bench_slip`` block of docs/benchmarks.md.

    .venv/bin/python bench/bench_slip.py                          # seeds 7-11, ~5 min
    .venv/bin/python bench/bench_slip.py --seeds 7 --no-docs       # ~1 min
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DOC_START, DOC_END = "<!-- bench_slip:start -->", "<!-- bench_slip:end -->"
#: (name, refine options) compared on every world
SETTINGS = (("prior off", {"slip_sigma_mps": None}), ("0.02 m/s (default)", {}))


def main(argv: list[str] | None = None) -> int:
    from bench.refine_worlds import BOX_WORLDS, run

    intro = ("`bench/bench_slip.py` (small hard world, {frames} frames, 5 cm / 1 deg labels, seeds {seeds}, each with "
             "movers on their box centres and on their rear axles (`rear_axle_fraction` 0.3); `bench_visibility`'s "
             "clip selection and scoring; other refinement settings at their defaults; docs/refinement.md, "
             "\"No side slip\").")
    return run(argv, __doc__.splitlines()[0], "7,8,9,10,11", BOX_WORLDS, SETTINGS,
               "The refinement's no-side-slip prior on noisy labels", intro, DOC_START, DOC_END)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
