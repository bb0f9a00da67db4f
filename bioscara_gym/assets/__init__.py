"""The MJCF model of the arm (``bioscara.xml``) and its scene (``scene.xml``).

Where every number in the model comes from is in ``README.md`` beside them.
This module only locates the files: it imports no MuJoCo.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def scene_path() -> Path:
    """Path of the scene (the arm, a table, a block and the goal marker)."""
    return Path(str(resources.files(__name__) / "scene.xml"))


__all__ = ["scene_path"]
