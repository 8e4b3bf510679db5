"""GSMN: the Grounded Semantic Mapping Network (Blukis et al., RSS 2018), re-implemented on MuJoCo."""

import os

# Headless rendering on the CPU. It must be set before mujoco is first imported, so it lives here.
os.environ.setdefault("MUJOCO_GL", "egl")
