"""Fixed (non-ψ) materials of the environments: diffuse RGB reflectances, the same in both domains.

Every mesh names a material (:class:`risp_data.envs.base.Mesh`): ``object`` takes the object
reflectance ψ (object_r/g/b); the names below are fixed colours that ψ does not touch, so the stored
Jacobians ∂I/∂ψ need no change for them.  They make the objects identifiable (docs/environments.md
§Appearance): the quadrotor's coloured front and left rotors, the stickers of the cube (one colour
per face), the hand's middle and distal phalanges, and the grey parts (rotor discs, rod posts).
Renderers (risp_data.render, risp_data's differentiable renderer) look colours up here.
"""

from __future__ import annotations

FIXED_MATERIALS: dict[str, tuple[float, float, float]] = {
    "rotor": (0.06, 0.06, 0.06),  # quadrotor back and right rotor discs, dark grey
    "rotor_front": (0.80, 0.06, 0.04),  # quadrotor front rotor (+x), red
    "rotor_left": (0.85, 0.85, 0.85),  # quadrotor left rotor (+y), white
    "post": (0.35, 0.35, 0.35),  # rod end posts
    "phalanx_middle": (0.92, 0.92, 0.92),  # hand: middle links of the three-link fingers, white
    "phalanx_distal": (0.80, 0.05, 0.05),  # hand: every finger's last link, red
    # the cube's face stickers, one colour per face value (cube.FACE_NORMALS)
    "sticker1": (0.80, 0.05, 0.05),  # red
    "sticker2": (0.05, 0.10, 0.75),  # blue
    "sticker3": (0.05, 0.55, 0.10),  # green
    "sticker4": (0.85, 0.70, 0.05),  # yellow
    "sticker5": (0.03, 0.03, 0.03),  # black
    "sticker6": (0.92, 0.92, 0.92),  # white
}


def material_color(name: str) -> tuple[float, float, float]:
    """RGB reflectance of a fixed material (KeyError names the known ones)."""
    try:
        return FIXED_MATERIALS[name]
    except KeyError:
        raise KeyError(f"unknown fixed material {name!r}; known: {', '.join(FIXED_MATERIALS)}") from None
