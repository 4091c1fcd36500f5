"""Does the GPU backend (``cuda_ad_rgb``) render what the CPU backend (``llvm_ad_rgb``) renders?

Two steps, on two machines:

    # here, on the CPU: render the references (images, Jacobians, state gradients) with llvm_ad_rgb
    PYTHONPATH=. python benchmarks/gpu_check.py reference --out benchmarks/gpu_reference.npz
    # on the GPU machine: the same states, looks and seeds with cuda_ad_rgb, compared with the references
    PYTHONPATH=. python benchmarks/gpu_check.py compare benchmarks/gpu_reference.npz [--json out.json]

For every environment, 2 sampled states × sampled train-domain looks (numpy generators seeded per case, so both
machines draw the same states and looks without storing them) are rendered at 32×32, 16 spp, with the
Jacobian J = ∂I/∂ψ by forward mode, and the state gradient ∂L/∂s of L = Σ w ⊙ I(s) (w a fixed smooth weight
image) through risp_data.diff_render.StateRenderer.  The comparison reports, per environment and quantity,
the relative difference ‖cuda − llvm‖ / ‖llvm‖ beside the Monte Carlo noise scale ‖llvm(seed) − llvm(seed')‖ /
‖llvm‖: the two backends draw the same random numbers, so their difference should sit far below that noise.
``compare`` also times the render of one image + J and one state-gradient step (medians after a warm-up).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

ENVS = ("quadrotor", "cube", "hand", "rod")
RES, SPP, CASES, SEED_A, SEED_B = 32, 16, 2, 11, 12


def _weight(res: int) -> np.ndarray:
    """A smooth, fixed weight image (res, res, 3): L = Σ w ⊙ I is then a generic smooth functional."""
    y, x = np.meshgrid(np.linspace(-1, 1, res), np.linspace(-1, 1, res), indexing="ij")
    w = np.stack([np.cos(2 * x) + 0.5 * y, np.sin(3 * y) * x + 1.0, 1.0 - x * y], -1)
    return w.astype(np.float32)


def render_all(variant: str) -> dict[str, np.ndarray]:
    """{env/quantity: array}: images and J for seeds A and B, and the state gradients for seed A."""
    import torch

    from risp_data.diff_render import StateRenderer
    from risp_data.envs import get_environment
    from risp_data.psi import sample_rendering
    from risp_data.render import Renderer

    out: dict[str, np.ndarray] = {}
    w = torch.from_numpy(_weight(RES)).double()
    for name in ENVS:
        env = get_environment(name)
        r = Renderer(name, "train", resolution=RES, spp=SPP, variant=variant)
        sr = StateRenderer(name, resolution=RES, spp=SPP, variant=variant)
        imgs, Js, imgs_b, Js_b, grads, grads_b = [], [], [], [], [], []
        for c in range(CASES):
            rng = np.random.default_rng(1000 + c)
            state = env.sample_states(rng, 1)[0]
            config = sample_rendering(name, "train", rng)
            for seed, I_list, J_list in ((SEED_A, imgs, Js), (SEED_B, imgs_b, Js_b)):
                img, J = r.render(state, config, seed=seed)
                I_list.append(img)
                J_list.append(J)
            for seed, g_list in ((SEED_A, grads), (SEED_B, grads_b)):
                s = torch.tensor(state[None], dtype=torch.float32, requires_grad=True)
                loss = (sr(s, seed=seed)[0].double() * w).sum()
                (g,) = torch.autograd.grad(loss, s)
                g_list.append(g[0].numpy())
        out[f"{name}/image"], out[f"{name}/J"] = np.stack(imgs), np.stack(Js)
        out[f"{name}/image_b"], out[f"{name}/J_b"] = np.stack(imgs_b), np.stack(Js_b)
        out[f"{name}/grad"], out[f"{name}/grad_b"] = np.stack(grads), np.stack(grads_b)
    return out


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm((a - b).ravel()) / max(np.linalg.norm(b.ravel()), 1e-12))


def timings(variant: str, repeats: int = 10) -> dict[str, float]:
    """Median seconds: one 64×64, 16 spp image + J (cube), one state-gradient step of one 64×64 frame (cube)."""
    import torch

    from risp_data.diff_render import StateRenderer
    from risp_data.envs import get_environment
    from risp_data.psi import sample_rendering
    from risp_data.render import Renderer

    env = get_environment("cube")
    rng = np.random.default_rng(0)
    r = Renderer("cube", "train", resolution=64, spp=16, variant=variant)
    sr = StateRenderer("cube", resolution=64, spp=16, variant=variant)
    states = env.sample_states(rng, repeats + 2)
    t_render, t_grad = [], []
    for i, state in enumerate(states):
        config = sample_rendering("cube", "train", rng)
        t0 = time.perf_counter()
        r.render(state, config, seed=i)
        t1 = time.perf_counter()
        s = torch.tensor(state[None], dtype=torch.float32, requires_grad=True)
        sr(s, seed=i).sum().backward()
        t2 = time.perf_counter()
        if i >= 2:  # the first two compile kernels
            t_render.append(t1 - t0)
            t_grad.append(t2 - t1)
    return {"render_image_and_J_s": float(np.median(t_render)), "state_gradient_step_s": float(np.median(t_grad))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("reference")
    a.add_argument("--out", required=True)
    a.add_argument("--variant", default="llvm_ad_rgb")
    b = sub.add_parser("compare")
    b.add_argument("reference")
    b.add_argument("--variant", default="cuda_ad_rgb")
    b.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    if args.cmd == "reference":
        np.savez_compressed(args.out, **render_all(args.variant))
        print(f"wrote {args.out}")
        return 0
    ref = np.load(args.reference)
    t0 = time.perf_counter()
    got = render_all(args.variant)
    rows = {"variant": args.variant, "wall_s": time.perf_counter() - t0, "envs": {}}
    print("| env | image: cuda vs llvm | image noise (seed vs seed) | J: cuda vs llvm | J noise | ∂L/∂s: cuda vs llvm | ∂L/∂s noise |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name in ENVS:
        e = {
            "image_rel_diff": _rel(got[f"{name}/image"], ref[f"{name}/image"]),
            "image_rel_noise": _rel(ref[f"{name}/image_b"], ref[f"{name}/image"]),
            "J_rel_diff": _rel(got[f"{name}/J"], ref[f"{name}/J"]),
            "J_rel_noise": _rel(ref[f"{name}/J_b"], ref[f"{name}/J"]),
            "grad_rel_diff": _rel(got[f"{name}/grad"], ref[f"{name}/grad"]),
            "grad_rel_noise": _rel(ref[f"{name}/grad_b"], ref[f"{name}/grad"]),
            "grad_cuda": got[f"{name}/grad"].tolist(),
            "grad_llvm": ref[f"{name}/grad"].tolist(),
        }
        rows["envs"][name] = e
        print(f"| {name} | {e['image_rel_diff']:.2e} | {e['image_rel_noise']:.2e} | {e['J_rel_diff']:.2e} | "
              f"{e['J_rel_noise']:.2e} | {e['grad_rel_diff']:.2e} | {e['grad_rel_noise']:.2e} |")
    rows["timings"] = timings(args.variant)
    print(json.dumps(rows["timings"]))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
