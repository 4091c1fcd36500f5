"""The paper's temporal-sampling ablation for the rod (``--table sampling``): the loss landscape vs log10 E.

For repeat k's target-domain rod reference video (``SAMPLING_FRAMES`` frames at 10 fps, a random log10 E in
[4, 7), a random sinusoidal force), the rod is simulated with its known force for each log10 E on a grid
of ``GRID`` values over [4, 7] and compared with the network's reading of the video,

    L_scheme(E) = mean_{t ∈ scheme} ‖τ(s_t(E)) − N(I_t)‖²

(the tasks' ``state`` loss: the RISP loss without rendering in the loop, for cost), on the frames that each
temporal-sampling scheme keeps: every frame, every 5th, first + last, first + middle.  A cell's value is
|argmin_E L − log10 E_true|; the report adds ``sampling.png`` (the landscapes).  The rollouts are shared by
the four schemes (cached per video and grid as ``<cache>/landscapes/*.npz``).
"""

from __future__ import annotations

import os

import numpy as np
import torch

SCHEMES: tuple[str, ...] = ("every-frame", "every-5th", "first-last", "first-middle")
SAMPLING_FRAMES = 11  # 1 s at 10 fps: every 5th keeps 0, 5, 10
GRID = {"quick": 5, "full": 25}
RANGE = (4.0, 7.0)


def scheme_frames(scheme: str, n: int) -> list[int]:
    return {"every-frame": list(range(n)), "every-5th": list(range(0, n, 5)), "first-last": [0, n - 1],
            "first-middle": [0, n // 2]}[scheme]


def landscape(cfg, art, repeat: int) -> dict:
    """{"grid": (G,), "losses": {scheme: (G,)}, "true": log10 E} for repeat k (cached)."""
    import json

    from risp_data.atomic import atomic_write
    from risp_data.envs import get_environment
    from risp_tasks.sims import get_simulator
    from risp_tasks.tasks.simulate import frame_states, initial_sim_state, steps_per_frame
    from risp_tasks.video import read_video
    from risp_train.predictor import load

    from .artifacts import checksum

    ref = art.video("rod", repeat, frames=SAMPLING_FRAMES)
    model = art.network("rod", "reg")
    grid = np.linspace(*RANGE, GRID["quick" if cfg.quick else "full"])
    path = os.path.join(art.root, "landscapes", f"rod-r{repeat}-{checksum([ref['video'], model, grid.tolist()])}.npz")
    with open(ref["truth"]) as f:
        truth = json.load(f)
    if not os.path.exists(path):
        env, sim = get_environment("rod"), get_simulator("rod")
        predictor = load(model)
        frames = torch.from_numpy(read_video(ref["video"], resolution=predictor.resolution).frames)
        with torch.no_grad():
            goal = predictor.predict(frames)[1].to(torch.float64)  # (T, targets) N(I_t)
        actions = torch.tensor(truth["actions"], dtype=torch.float64)
        s0 = initial_sim_state(sim, torch.tensor(truth["env_states"][0], dtype=torch.float64), None, truth["fps"])
        k = steps_per_frame(sim, truth["fps"])
        per_frame = []
        for value in grid:
            params = sim.default_params()
            params[0, sim.param_index("log10_E")] = float(value)
            with torch.no_grad():
                states = frame_states(sim, params, s0, actions, len(goal), k)
            per_frame.append(((env.state_to_target(states) - goal) ** 2).sum(-1).numpy())
        with atomic_write(path, "wb", suffix=".npz") as f:
            np.savez(f, grid=grid, per_frame=np.stack(per_frame))  # (G, T)
    with np.load(path) as data:  # closed at once (a table run opens one per repeat)
        grid, per_frame = data["grid"], data["per_frame"]
    n = per_frame.shape[1]
    return {"grid": grid, "true": float(truth["params"]["log10_E"]),
            "losses": {s: per_frame[:, scheme_frames(s, n)].mean(1) for s in SCHEMES}}


def sampling(cfg, art, env_name: str, scheme: str, repeat: int) -> dict:
    if env_name != "rod":
        return {"na": "the temporal-sampling ablation is the rod's (paper)"}
    land = landscape(cfg, art, repeat)
    losses = land["losses"][scheme]
    best = float(land["grid"][int(np.argmin(losses))])
    return {"value": abs(best - land["true"]), "metric": "|argmin log10 E − true|", "argmin": best,
            "true": land["true"], "grid": land["grid"].tolist(), "losses": losses.tolist()}


def plot_sampling(results: list[dict], path: str, *, seed: int) -> None:
    """Normalised loss landscapes L/max L vs log10 E per scheme, one panel per repeat; the truth dashed."""
    from risp_data.figures import subplots

    from risp_data.figures import save_figure

    rows = [r for r in results if "losses" in r]
    repeats = sorted({r["repeat"] for r in rows})
    if not repeats:
        return
    fig, axes = subplots(1, len(repeats), figsize=(3.4 * len(repeats), 3.0), squeeze=False)
    for ax, k in zip(axes[0], repeats):
        for r in (r for r in rows if r["repeat"] == k):
            losses = np.asarray(r["losses"])
            ax.plot(r["grid"], losses / max(losses.max(), 1e-30), "o-", ms=3, label=r["method"])
            ax.axvline(r["true"], color="k", ls="--", lw=0.8)
        ax.set(title=f"rod, repeat {k}", xlabel="log10 E", ylabel="loss / max")
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, seed=seed, what="risp-task table --table sampling: loss vs log10 E")
