"""Object pixel coverage per environment at the training resolution (issue 8, item 2; docs/environments.md).

For N sampled states of each environment (its own sampler, seeded), a primary ray through every pixel
centre of the environment's camera is intersected with the Mitsuba scene; a pixel counts as an object
pixel when it hits a mesh of the object (every mesh but the floor and the rod's fixed posts).  Reported
per environment, min / median / max over the samples of

* ``pixels``: object pixels in the W × W image,
* ``across``: the larger side of the object pixels' bounding box, in pixels.

    python benchmarks/object_coverage.py [--n 200] [--res 64] [--envs quadrotor,cube,hand,rod]

Geometry only (no shading); takes seconds.  Prints a markdown table and, with --json, writes the numbers;
with --png, also renders the first 6 sampled states of each environment in both domains (64×64, 16 spp,
the target domain by its reference integrator) into one contact sheet (docs/img/objects_64px.png).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from risp_data.envs import ENV_NAMES, get_environment  # noqa: E402
from risp_data.render import Renderer  # noqa: E402

NOT_OBJECT = ("floor", "mesh_post")  # shape ids that are scenery


def object_masks(env_name: str, states: np.ndarray, res: int) -> np.ndarray:
    """(N, res, res) bool: pixel centre's primary ray hits the object."""
    r = Renderer(env_name, "train", resolution=res, spp=1)
    mi, dr = r._mi, r._dr
    sensor = r.scene.sensors()[0]
    ij = np.stack(np.meshgrid(np.arange(res), np.arange(res), indexing="xy"), -1).reshape(-1, 2)
    uv = mi.Point2f(*[mi.Float(((ij[:, k] + 0.5) / res).astype(np.float32)) for k in range(2)])
    object_shapes = [s for s in r.scene.shapes() if s.id() not in NOT_OBJECT]
    masks = []
    for state in states:
        r.set_state(state)
        r.params.update()
        ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5), uv, mi.Point2f(0.5, 0.5))
        si = r.scene.ray_intersect(ray)
        hit = dr.zeros(mi.Bool, res * res)
        for shape in object_shapes:
            hit |= si.is_valid() & (si.shape == mi.ShapePtr(shape))
        masks.append(np.array(hit, dtype=bool).reshape(res, res))
    return np.stack(masks)


def coverage(env_name: str, n: int, res: int, seed: int = 0) -> dict:
    env = get_environment(env_name)
    states = env.sample_states(np.random.default_rng(seed), n)
    masks = object_masks(env_name, states, res)
    pixels = masks.sum((1, 2))
    across = []
    for m in masks:
        rows, cols = np.nonzero(m.any(1))[0], np.nonzero(m.any(0))[0]
        across.append(max(np.ptp(rows) + 1, np.ptp(cols) + 1) if rows.size else 0)
    across = np.asarray(across)
    stats = {}
    for name, a in (("pixels", pixels), ("across", across)):
        stats[name] = {"min": int(a.min()), "median": float(np.median(a)), "max": int(a.max())}
    return {"env": env_name, "n": n, "res": res, "seed": seed, **stats}


def contact_sheet(envs: list[str], res: int, png: str, cols: int = 6) -> None:
    """Rows (env, domain), columns: sampled states rendered with sampled rendering parameters."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from risp_data.psi import sample_rendering

    rows = [(e, d) for e in envs for d in ("train", "target")]
    fig, axes = plt.subplots(len(rows), cols, figsize=(1.6 * cols, 1.7 * len(rows)), squeeze=False)
    for row, (env_name, domain) in enumerate(rows):
        r = Renderer(env_name, domain, resolution=res, spp=16)
        rng = np.random.default_rng(row)
        states = get_environment(env_name).sample_states(rng, cols)
        for k in range(cols):
            img = r.render_reference(states[k], sample_rendering(env_name, domain, rng), seed=k)
            axes[row, k].imshow(np.clip(img, 0, 1) ** (1 / 2.2))
            axes[row, k].set_xticks([])
            axes[row, k].set_yticks([])
        axes[row, 0].set_ylabel(f"{env_name}\n{domain}", fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=90)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--envs", default=",".join(ENV_NAMES))
    ap.add_argument("--json", default=None)
    ap.add_argument("--png", default=None, help="also write a contact sheet of renders in both domains")
    args = ap.parse_args()
    rows = [coverage(e, args.n, args.res) for e in args.envs.split(",")]
    print(f"Object coverage at {args.res}×{args.res}, {args.n} sampled states each (min / median / max)\n")
    print("| env | object pixels | pixels across |\n|---|---|---|")
    for r in rows:
        p, a = r["pixels"], r["across"]
        print(f"| {r['env']} | {p['min']} / {p['median']:g} / {p['max']} | {a['min']} / {a['median']:g} / {a['max']} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    if args.png:
        contact_sheet(args.envs.split(","), args.res, args.png)


if __name__ == "__main__":
    main()
