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


# muted, distinguishable link colours (matplotlib's tab10, lightened) for visuals without a material
_LINK_PALETTE = ((0.45, 0.62, 0.81), (1.00, 0.66, 0.38), (0.50, 0.78, 0.50), (0.90, 0.50, 0.50),
                 (0.70, 0.60, 0.83), (0.72, 0.58, 0.54), (0.93, 0.64, 0.84), (0.65, 0.65, 0.65),
                 (0.80, 0.80, 0.45), (0.45, 0.80, 0.85))


SKELETON_COLOR = np.array([0.30, 0.45, 0.69, 1.0])  # a URDF without visuals, drawn as its skeleton


def skeleton_radii(skeleton) -> tuple[float, float]:
    """(joint sphere, rod) radii of the skeleton drawn for a URDF without visuals ({link:
    offsets of the links attached to it}): 4% and 2% of its longest rod, at least 3 and 1.5 cm,
    so that a robot metres long is not drawn as a hairline."""
    longest = max((float(np.linalg.norm(offset)) for offsets in skeleton.values() for offset in offsets), default=0.0)
    return max(0.03, 0.04 * longest), max(0.015, 0.02 * longest)


def link_color(visual, materials, link_index: int):
    """The RGBA colour a viewer draws a URDF <visual> in: its material's (`urdf_color`), else
    link `link_index`'s colour from a palette of distinct colours, so that a robot whose file
    names no colours shows its links apart rather than all grey."""
    color = urdf_color(visual, materials)
    if color is not None:
        return color
    return np.array([*_LINK_PALETTE[link_index % len(_LINK_PALETTE)], 1.0])
