"""FAST-Hex vehicle model, full-pose geometric controller, wrench mapper and tilt planner.
Pure numerics, no I/O."""
