"""Render one sample of an environment with its Jacobian stack and save it as a PNG.

    python scenes/hello_render.py --env quadrotor --domain target --out hello.png
"""

import argparse

import numpy as np

from risp_data.psi import sample_rendering
from risp_data.render import Renderer


def main(argv=None) -> None:
    """Parse the options, render one sample and write the PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ap = argparse.ArgumentParser()
    ap.add_argument("--env", default="cube")
    ap.add_argument("--domain", default="train")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="hello.png")
    args = ap.parse_args(argv)

    renderer = Renderer(args.env, args.domain, resolution=128, spp=32)
    rng = np.random.default_rng(args.seed)                      # explicit seed: same picture every time
    state = renderer.env.sample_states(rng, 1)[0]               # a pose the simulator could produce
    config = sample_rendering(args.env, args.domain, rng)       # ψ (8,) and non-differentiable aux
    image, J = renderer.render(state, config, seed=args.seed)   # (128, 128, 3), (8, 128, 128, 3)

    fig, axes = plt.subplots(1, 1 + len(J), figsize=(2 * (1 + len(J)), 2.3))
    axes[0].imshow(np.clip(image, 0, 1) ** (1 / 2.2))
    axes[0].set_title("image")
    for ax, name, Jj in zip(axes[1:], renderer.psi_names, J):
        lim = np.abs(Jj.sum(-1)).max() + 1e-12
        ax.imshow(Jj.sum(-1), cmap="RdBu_r", vmin=-lim, vmax=lim)   # ∂I/∂ψ_j summed over RGB
        ax.set_title(name, fontsize=8)
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(args.out, dpi=80)
    print(f"wrote {args.out}: state {np.round(state, 3)}, psi {np.round(config.psi, 3)}")


if __name__ == "__main__":
    main()
