"""Closed-loop evaluation of policies in the generation tasks, per split.

Owns the gym environments (`env`: keyframe policies, whose predicted keyframes are reached with the rollout's
planner; dense policies acting every control tick), the policies evaluated (`policies`: a LeRobot checkpoint,
the expert, the current pose), the runner and results (`runner`), ``demo-factory eval`` (`cli`) and the
``lerobot-eval`` EnvConfig (`lerobot_env`). Reads a converted dataset's provenance (its variations,
instructions and export) and a checkpoint; writes ``results.json``, ``results.md``, ``results.png``,
``episodes.jsonl`` and, on request, each rollout as an MCAP recording.
"""
