"""What the 3-D views share of a URDF's `<visual>` elements (as yourdfpy reads them): MeshCat's
scene (`_meshcat.py`) and MuJoCo's offscreen movies (`_puppet.py`) paint a visual alike."""

from __future__ import annotations

import numpy as np


def urdf_color(visual, materials):
    """The RGBA colour of a URDF <visual> (its own material's, else the named robot material's),
    or None."""
    if visual.material is not None:
        for source in (visual.material, materials.get(visual.material.name)):
            if source is not None and source.color is not None:
                return np.asarray(source.color.rgba, float)
    return None
