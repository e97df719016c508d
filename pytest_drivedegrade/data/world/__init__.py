"""The embedded world: a procedurally generated surround-view driving world written in nuScenes format.

`write_world` renders one anywhere; `ensure_default_world` generates the suite's default once into pytest's
cache (atomically, safe under xdist) and reuses it. See `scene.py` (what is in a scene), `expert.py` (how the
ego drives), `render.py` (the cameras) and `export.py` (the tables).
"""

from __future__ import annotations

from .build import DEFAULT_SCENES, GENERATOR_VERSION, WORLD_VERSION, cli_world, ensure_default_world, write_world

__all__ = ["DEFAULT_SCENES", "GENERATOR_VERSION", "WORLD_VERSION", "cli_world", "ensure_default_world",
           "write_world"]
