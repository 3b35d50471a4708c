"""Maintainers' tools, run from the Makefile; no stage of the pipeline imports them.

- `bench` (``make bench``): generation, planner, camera, conversion and HiveFormer figures → ``bench/results.json``.
- `reference_run` (``make reference``, ``make reference-act``): the whole chain, generate → convert →
  ``lerobot-train`` → closed-loop eval, for HiveFormer on keyframes or ACT on dense frames → ``outputs/``.
- `cards` (``make cards``): regenerates the committed cards of the standard datasets in ``dataset_cards/``.
"""
