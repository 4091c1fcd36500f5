"""What an environment looks like, as one short checksum: its camera, its meshes at a reference state and
the fixed colours of their materials.

Rendered data and everything made from it (networks, tables' cells) depend on the look; the look changes
when risp changes an environment's appearance (the cube's stickers and the hand's marked phalanges replaced
a look that could not be read: docs/environments.md §Appearance).  The fingerprint is stored in every shard
manifest, and a folder of another look is not resumed; the tables key their data sets and cells by it, so a
new look never mixes with finished work of an old one.
"""

from __future__ import annotations

import functools
import hashlib
import json

import numpy as np
import torch

from . import get_environment
from .materials import FIXED_MATERIALS


@functools.lru_cache(maxsize=None)
def look_fingerprint(name: str) -> str:
    """First 12 hex digits of the sha256 of the look of environment ``name`` (camera, floor, every mesh's
    name, material, fixed colour, faces and its vertices at the middle of the documented state range)."""
    env = get_environment(name)
    s_ref = (torch.tensor(env.state_low, dtype=torch.float64) + torch.tensor(env.state_high, dtype=torch.float64)) / 2
    meshes = []
    for m in env.meshes(s_ref):
        meshes.append({
            "name": m.name,
            "material": m.material,
            "colour": None if m.material == "object" else list(FIXED_MATERIALS[m.material]),
            "faces": m.faces.tolist(),
            # rounded: the fingerprint must not depend on the last bits of a platform's trigonometry
            "vertices": (np.round(m.vertices.detach().numpy().astype(np.float64), 6) + 0.0).tolist(),  # no −0.0
        })
    look = {"camera": [list(env.camera.origin), list(env.camera.target), list(env.camera.up), env.camera.fov],
            "floor_height": env.floor_height, "meshes": meshes}
    return hashlib.sha256(json.dumps(look, sort_keys=True).encode()).hexdigest()[:12]
