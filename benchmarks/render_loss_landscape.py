"""Where the sysid losses have their minimum: landscapes over one identified parameter (docs/RESULTS.md §Where the
render loss has its minimum).

    PYTHONPATH=. python benchmarks/render_loss_landscape.py MODEL v200.mp4 [v201.mp4 …] [--grid 25] [--every 2]
        [--variants state,nominal,seeds,looks] [--k 4] [--spp 4] [--primal-spp 4] [--plot landscapes.png] [--json out.json]

For each make-video reference video (its ``<stem>.truth.json`` beside it: commands, start, parameter, which no
solver reads) the system is simulated with the true commands and start for every value θ of the identified
parameter on a grid over its sampling range (``sysid``'s: rod log10 E [4, 7), quadrotor mass [2.8, 3.2)), and on
the frames ``sysid --every`` keeps the loss is evaluated with sysid's default residual (L1 in the network's target
space, docs/tasks.md §Residual norm):

    state   L(θ) = mean_t ‖τ(s_t(θ)) − N(I_t)‖₁                     (``--loss state``)
    nominal L(θ) = mean_t ‖N(R_ψ0(s_t(θ))) − N(I_t)‖₁               (``--loss render``: the train domain's nominal look ψ0)
    seeds   the same with N's readings averaged over K renders of ψ0 with other sampler seeds
    looks   the same with N's readings averaged over K random train-domain looks ψ_1…ψ_K (seed 123)

Printed per video and variant: |argmin_θ L − θ_true|, and the means with their ratio to a random guess's expected
error over the range, E|U − θ_true| = ((θ_true − a)² + (b − θ_true)²) / (2 (b − a)).  The grid's step bounds the
resolution (0.125 for the rod at 25 points).  One thread each for torch and Dr.Jit.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

VARIANTS = ("state", "nominal", "seeds", "looks")
ONE_PARAMETER = ("rod", "quadrotor")  # sysid identifies one parameter there (the hand five, the cube no commands)


def truth_of(video: Path) -> dict:
    path = video.with_name(video.stem + ".truth.json")
    if not path.exists():
        raise SystemExit(f"{video}: no {path.name} beside it (a make-video reference video's ground truth)")
    with open(path) as f:
        return json.load(f)


def start_of(truth: dict, sim):
    """The simulator's true start (1, X): make-video's recorded one, else from the first two frames' true states."""
    import torch

    from risp_tasks.tasks.simulate import initial_sim_state

    if truth.get("sim_states") is not None:
        return torch.tensor(truth["sim_states"][0], dtype=torch.float64)[None]
    first, second = (torch.tensor(truth["env_states"][i], dtype=torch.float64) for i in (0, 1))
    return initial_sim_state(sim, first, second, truth["fps"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("videos", nargs="+")
    ap.add_argument("--grid", type=int, default=25)
    ap.add_argument("--every", type=int, default=2)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--k", type=int, default=4, help="renders averaged by the seeds and looks variants")
    ap.add_argument("--spp", type=int, default=4, help="samples per pixel of the renders (sysid's default --spp)")
    ap.add_argument("--primal-spp", type=int, default=None, help="of the renders N reads (default --spp)")
    ap.add_argument("--plot", default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    variants = args.variants.split(",")
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise SystemExit(f"unknown variant(s) {', '.join(unknown)}; choose from {', '.join(VARIANTS)}")

    import drjit as dr
    import torch

    import risp_train
    from risp_data.diff_render import StateRenderer
    from risp_data.envs import get_environment
    from risp_data.psi import sample_rendering
    from risp_tasks.sims import get_simulator
    from risp_tasks.tasks.simulate import frame_states, steps_per_frame, to_sim_actions
    from risp_tasks.tasks.sysid import IDENTIFIED, parameter_ranges
    from risp_tasks.demo import random_guess_error
    from risp_tasks.video import read_video, sha256_file

    torch.set_num_threads(1)
    dr.set_thread_count(1)
    predictor = risp_train.load(args.model)
    env_name = predictor.env_name
    if env_name not in ONE_PARAMETER:
        raise SystemExit(f"the landscape is over one parameter: {', '.join(ONE_PARAMETER)} (the model is {env_name}'s)")
    env, sim = get_environment(env_name), get_simulator(env_name)
    name = IDENTIFIED[env_name][0]
    low, high = parameter_ranges(sim)[name]
    grid = np.linspace(low, high, args.grid)
    renderer = StateRenderer(env_name, resolution=predictor.resolution, spp=args.spp, primal_spp=args.primal_spp)
    nominal = renderer.config
    rng = np.random.default_rng(123)
    looks = [sample_rendering(env_name, "train", rng) for _ in range(args.k)]

    def read(images):
        with torch.no_grad():
            return predictor.predict(images.float())[1].double()

    def render(states, look, seed):
        renderer.set_look(look)
        return read(renderer(states.float(), seed=seed))

    rows, curves, started = [], {}, time.perf_counter()
    for video in map(Path, args.videos):
        truth = truth_of(video)
        if truth["env"] != env_name:
            raise SystemExit(f"{video}: a {truth['env']} video, the model is {env_name}'s")
        if truth.get("video_sha256") and truth["video_sha256"] != sha256_file(video):
            raise SystemExit(f"{video}: its truth file was written for another video (video_sha256 differs)")
        frames = torch.as_tensor(read_video(video, resolution=predictor.resolution).frames)
        keep = list(range(0, len(frames), args.every))
        goal = read(frames)[keep]
        actions = torch.tensor(truth["actions"], dtype=torch.float64)
        s0 = start_of(truth, sim)
        k = steps_per_frame(sim, truth["fps"])
        losses = {v: [] for v in variants}
        for value in grid:
            params = sim.default_params()
            params[0, sim.param_index(name)] = float(value)
            with torch.no_grad():  # the file's actions in simulator units (quadrotor thrusts [N] -> u = f / k_f)
                states = frame_states(sim, params, s0, to_sim_actions(sim, params, actions), len(frames), k)[keep]

            def residual(targets):
                return float((targets - goal).abs().sum(-1).mean())

            for v in variants:
                if v == "state":
                    losses[v].append(residual(env.state_to_target(states).double()))
                elif v == "nominal":
                    losses[v].append(residual(render(states, nominal, 0)))
                elif v == "seeds":
                    losses[v].append(residual(torch.stack([render(states, nominal, 100 + j)
                                                           for j in range(args.k)]).mean(0)))
                else:
                    losses[v].append(residual(torch.stack([render(states, look, 0) for look in looks]).mean(0)))
        true = float(truth["params"][name])
        row = {"video": str(video), "true": true, "random": random_guess_error(true, low, high),
               **{v: abs(float(grid[int(np.argmin(losses[v]))]) - true) for v in variants}}
        rows.append(row)
        curves[str(video)] = {v: losses[v] for v in variants}
        print(video.name, f"true {name} {true:.3f}", " ".join(f"{v} {row[v]:.3f}" for v in variants), flush=True)
    rnd = float(np.mean([r["random"] for r in rows]))
    summary = {v: {"mean_error": float(np.mean([r[v] for r in rows])),
                   "ratio_to_random": float(np.mean([r[v] for r in rows]) / rnd)} for v in variants}
    print(f"{len(rows)} videos, {name}: random guess {rnd:.4f}; " +
          "; ".join(f"{v} {s['mean_error']:.4f} ({s['ratio_to_random']:.3f}x)" for v, s in summary.items()) +
          f"  [{time.perf_counter() - started:.0f} s]")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"model": args.model, "parameter": name, "grid": grid.tolist(), "args": vars(args),
                       "rows": rows, "summary": summary, "losses": curves}, f, indent=1)
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        n = len(rows)
        cols = min(4, n)
        fig, axes = plt.subplots((n + cols - 1) // cols, cols, figsize=(3.2 * cols, 2.4 * ((n + cols - 1) // cols)),
                                 squeeze=False)
        for ax, row in zip(axes.flat, rows):
            for v in variants:
                y = np.asarray(curves[row["video"]][v])
                ax.plot(grid, (y - y.min()) / max(np.ptp(y), 1e-12), label=v)
            ax.axvline(row["true"], color="k", lw=0.8, ls="--")
            ax.set_title(Path(row["video"]).stem, fontsize=8)
        for ax in list(axes.flat)[n:]:
            ax.axis("off")
        axes.flat[0].legend(fontsize=6)
        fig.supxlabel(name)
        fig.supylabel("loss (min–max scaled)")
        fig.tight_layout()
        fig.savefig(args.plot, dpi=110)


if __name__ == "__main__":
    main()
