"""A tiny trained predictor per environment for the task tests: a handful of real renders (16×16, 2 spp) and
one short real training run (risp_train.fit), cached per test session."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

RES = 16


def box_mesh(center, half):
    """(V (8, 3), F (12, 3)) of an axis-aligned box with outward faces."""
    c, h = np.asarray(center, float), np.asarray(half, float)
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * h + c
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def write_obj(path, parts):
    """A Wavefront OBJ with one named object (``o NAME``) per part."""
    lines, offset = [], 0
    for name, (v, f) in parts.items():
        lines.append(f"o {name}")
        lines += [f"v {a:.6f} {b:.6f} {c:.6f}" for a, b, c in v]
        lines += [f"f {a + 1 + offset} {b + 1 + offset} {c + 1 + offset}" for a, b, c in f]
        offset += len(v)
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def vehicle_obj(tmp_path, scale=1.0, name="vehicle.obj"):
    """A plain box 'frame' (0.5 × 0.5 × 0.1 m) with a red front rotor box at +x, in metres (× scale)."""
    frame = box_mesh((0, 0, 0), (0.25, 0.25, 0.05))
    front = box_mesh((0.3, 0, 0.05), (0.08, 0.08, 0.01))
    return write_obj(tmp_path / name, {"frame": (frame[0] * scale, frame[1]),
                                       "rotor_front": (front[0] * scale, front[1])})


def tiny_model(root, env: str, n: int = 16) -> str:
    from risp_train.config import make_config
    from risp_train.train import fit

    shards = root / f"shards-{env}"
    cmd = [sys.executable, "-m", "risp_data", "render", "--env", env, "--n", str(n), "--res", str(RES), "--spp", "2",
           "--shard-size", str(n), "--seed", "0", "--workers", "1", "--quiet", "--out", str(shards)]
    subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=300)
    cfg = make_config(str(shards), str(root / "runs" / env), preset="cpu", epochs=1, batch_size=4, width=4, workers=0,
                      lr=3e-3, shuffle_buffer=8, stats_samples=n, reg="none")
    return str(fit(cfg, progress=False))


_CACHE: dict = {}


def shared_model(tmp_path_factory, env: str) -> str:
    """One tiny model per environment for the whole test session."""
    if env not in _CACHE:
        _CACHE[env] = tiny_model(tmp_path_factory.mktemp(f"tiny-{env}"), env)
    return _CACHE[env]


def shared_video(tmp_path_factory, env: str, frames: int = 6) -> str:
    """A small target-domain reference video (+ .truth.json, .actions.csv) per environment."""
    key = ("video", env, frames)
    if key not in _CACHE:
        from risp_tasks.tasks.reference import ReferenceConfig, make_reference

        out = str(tmp_path_factory.mktemp(f"video-{env}") / f"{env}.mp4")
        make_reference(ReferenceConfig(env=env, out=out, frames=frames, resolution=RES, spp=2, seed=3, progress=False))
        _CACHE[key] = out
    return _CACHE[key]
