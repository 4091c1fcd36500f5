"""How well do the state gradients of risp_data.diff_render match central differences, per environment?

For every environment, a random state s and the loss L(s) = Σ w ⊙ I(s) (w a smooth weight image), the
script compares the state gradient ∂L/∂s from the projective integrator (averaged over seeds) with the
central difference of every state coordinate, (L(s + ε e_i) − L(s − ε e_i)) / 2ε, from images rendered with
the same seeds (float64 sums of float32 images).  It prints, per environment, the cosine similarity of the
two vectors, the relative error ‖g − fd‖ / ‖fd‖, and the FD's own standard error (across seeds), for

    mitsuba  — Mitsuba's ``prb_projective`` as is (guiding off), gradient and primal at the domain's depth;
    risp     — risp_data.diff_render.StateRenderer (flat-shading boundary terms, point-light shadows,
               gradient paths of 2 segments; primal by the data renderer's own integrator).

ε = 1e-2 (m or rad) moves silhouettes by a few tenths of a pixel at 32×32: small enough for the change to be
nearly linear, large enough that the same-seed difference is not dominated by single samples flipping.

    PYTHONPATH=. OMP_NUM_THREADS=1 python benchmarks/diff_render_fd.py [--envs cube,rod] [--seeds 3]

``--descent N``: instead, recover the first three state coordinates (the position of the cube and the
quadrotor) from a pixelwise L2 loss against an image rendered at that state, starting (4, −3, 2.5)·1e-2 off,
with N Adam steps (lr 5e-3), and print the error norm before and after, per gradient: does descent still
converge where the gradient is biased?
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch


def weights(res: int) -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.linspace(0, 1, res), torch.linspace(0, 1, res), indexing="ij")
    return (torch.sin(3 * xx + 1) + torch.cos(2 * yy))[None, :, :, None].expand(1, res, res, 3).float()


def mitsuba_renderer(env: str, res: int, spp: int):
    """A StateRenderer whose gradient and primal are Mitsuba's own prb_projective (the state before the fix)."""
    import mitsuba as mi

    from risp_data.diff_render import StateRenderer

    r = StateRenderer(env, resolution=res, spp=spp)
    settings = r.renderer.settings
    r.integrator = mi.load_dict({"type": "prb_projective", "max_depth": settings.max_depth,
                                 "rr_depth": settings.rr_depth, "guiding": "none"})
    r.primal_integrator = r.integrator
    r._render_frame = r._make_frame_renderer()
    return r


def compare(r, s0: torch.Tensor, res: int, seeds: int, eps: float, fd_spp_factor: int = 1):
    """(gradient, FD, FD standard error) of L = Σ w ⊙ I along every state coordinate, averaged over seeds."""
    w = weights(res)
    S = s0.numel()
    grads, fds = [], []
    for seed in range(seeds):
        s = s0.clone().requires_grad_(True)
        (r(s[None], seed=seed) * w).sum().backward()
        grads.append(s.grad.numpy().copy())
        fd = np.zeros(S)
        with torch.no_grad():
            for i in range(S):
                e = torch.zeros(S, dtype=s0.dtype)
                e[i] = eps
                plus = (r((s0 + e)[None], seed=seed) * w).sum().double()
                minus = (r((s0 - e)[None], seed=seed) * w).sum().double()
                fd[i] = float((plus - minus) / (2 * eps))
        fds.append(fd)
    fds = np.array(fds)
    return np.mean(grads, 0), fds.mean(0), fds.std(0, ddof=1) / np.sqrt(seeds) if seeds > 1 else np.zeros(S)


def descent(r, s_true: torch.Tensor, res: int, steps: int, seed: int = 0) -> tuple[float, float]:
    """(start, end) error norm of s[:3] under Adam on ‖I(s) − I(s_true)‖² over s[:3] (the rest fixed)."""
    with torch.no_grad():
        target = r(s_true[None], seed=10_000)
    offset = torch.tensor([0.04, -0.03, 0.025], dtype=s_true.dtype)
    pos = (s_true[:3] + offset).clone().requires_grad_(True)
    opt = torch.optim.Adam([pos], lr=5e-3)
    start = float((pos - s_true[:3]).norm())
    for k in range(steps):
        opt.zero_grad()
        s = torch.cat([pos, s_true[3:]])
        ((r(s[None], seed=seed + k) - target) ** 2).mean().backward()
        opt.step()
    return start, float((pos.detach() - s_true[:3]).norm())


def main():
    from risp_data.envs import ENV_NAMES, get_environment
    from risp_data.mitsuba_setup import init_mitsuba

    ap = argparse.ArgumentParser()
    ap.add_argument("--envs", default=",".join(ENV_NAMES))
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--res", type=int, default=32)
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--eps", type=float, default=1e-2)
    ap.add_argument("--state-seed", type=int, default=1)
    ap.add_argument("--which", default="mitsuba,risp")
    ap.add_argument("--descent", type=int, default=0)
    a = ap.parse_args()
    torch.set_num_threads(1)
    init_mitsuba()
    from risp_data.diff_render import StateRenderer

    print(f"res {a.res}, spp {a.spp}, eps {a.eps}, seeds {a.seeds}, state seed {a.state_seed}, "
          f"load {os.getloadavg()[0]:.1f}")
    for env in a.envs.split(","):
        environment = get_environment(env)
        s0 = torch.tensor(environment.sample_states(np.random.default_rng(a.state_seed), 1)[0])
        for which in a.which.split(","):
            t0 = time.time()
            r = mitsuba_renderer(env, a.res, a.spp) if which == "mitsuba" else StateRenderer(env, a.res, a.spp)
            if a.descent:
                e0, e1 = descent(r, s0, a.res, a.descent)
                print(f"{env:9s} {which:8s} error of s[:3] {e0:.3f} -> {e1:.3f} after {a.descent} "
                      f"Adam steps ({time.time() - t0:.0f} s)", flush=True)
                continue
            g, fd, se = compare(r, s0, a.res, a.seeds, a.eps)
            cos = float(g @ fd / (np.linalg.norm(g) * np.linalg.norm(fd) + 1e-30))
            rel = float(np.linalg.norm(g - fd) / (np.linalg.norm(fd) + 1e-30))
            print(f"{env:9s} {which:8s} cos {cos:+.3f}  |g-fd|/|fd| {rel:.3f}  |fd| {np.linalg.norm(fd):8.2f}  "
                  f"fd s.e. {np.linalg.norm(se):.2f}  ({time.time() - t0:.0f} s)", flush=True)
            print("   g  ", np.array2string(g, precision=1, suppress_small=True, max_line_width=200))
            print("   fd ", np.array2string(fd, precision=1, suppress_small=True, max_line_width=200))


if __name__ == "__main__":
    main()
