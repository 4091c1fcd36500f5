"""Benchmark: seconds per optimisation iteration of the tasks, per environment and loss mode, and the share
spent in simulation, rendering and the network (issue 10; targets ≤ 3 s render mode, ≤ 0.3 s state mode).

    python benchmarks/bench_tasks.py                       # every env, 8 frames, 64×64, spp 4, cpu-preset net
    python benchmarks/bench_tasks.py --envs quadrotor --repeats 5
    python benchmarks/bench_tasks.py --envs rod --looks 4  # also render mode reading K random looks (--looks)

One iteration = imitate's: roll the simulator out over 8 frames at 10 fps (k = 10 steps per frame; the cube,
having no actions, differentiates its parameters instead), render the frames (render mode), run the
network (ResNet-18 topology at the cpu preset's width 16, random weights — the cost does not depend on them),
loss, backward.  The shares come from separately timed forward+backward passes of each stage on the same
inputs (medians); "total" is the median of whole iterations.  One torch thread, Dr.Jit's default threads.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import torch


def _median_time(fn, repeats):
    out = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        out.append(time.perf_counter() - start)
    return statistics.median(out)


def bench_env(env_name: str, frames: int, res: int, spp: int, repeats: int, gradient: str = "flat",
              looks: int = 1) -> dict:
    from risp_data.diff_render import StateRenderer
    from risp_data.envs import get_environment
    from risp_train.model import ModelConfig, ResNet18, stem_for_resolution
    from risp_train.normalization import Normalization
    from risp_train.predictor import RispPredictor
    from risp_tasks.sims import get_simulator
    from risp_tasks.tasks.simulate import action_centre, frame_states, initial_sim_state, steps_per_frame

    env, sim = get_environment(env_name), get_simulator(env_name)
    T = env.target_dim
    net = ResNet18(ModelConfig(out_dim=T, width=16, stem=stem_for_resolution(res)))
    norm = Normalization((0.1,) * 3, (0.2,) * 3, (0.0,) * T, (1.0,) * T)
    predictor = RispPredictor(net, norm, env_name, env.state_names, env.target_names, res).eval()
    for p in predictor.parameters():
        p.requires_grad_(False)
    renderer = StateRenderer(env_name, resolution=res, spp=spp, boundary=gradient)
    k = steps_per_frame(sim, 10.0)
    params = sim.default_params()
    mid = torch.tensor([(a + b) / 2 for a, b in zip(env.state_low, env.state_high)], dtype=torch.float64)
    s0 = initial_sim_state(sim, mid, None, 10.0)
    goal = torch.zeros(frames, T)

    def variables():
        if sim.action_dim:
            return action_centre(sim, params).expand(frames, -1).clone().requires_grad_(True)
        return params.clone().requires_grad_(True)

    def simulate(v):
        if sim.action_dim:
            return frame_states(sim, params, s0, v, frames, k)
        return frame_states(sim, v, s0, None, frames, k)

    def sim_only():
        simulate(variables()).sum().backward()

    states = simulate(variables()).detach().float()

    def render_only():
        s = states.clone().requires_grad_(True)
        renderer(s, seed=0).sum().backward()

    images = renderer(states, seed=0).detach()

    def network_only():
        x = images.clone().requires_grad_(True)
        predictor.predict(x)[1].sum().backward()

    from risp_tasks.tasks.loop import make_loss
    from risp_tasks.tasks.run import render_looks

    several = render_looks(env_name, looks, 0)
    nominal = renderer.config
    looks_loss = make_loss("render", env, list(range(frames)), goal.double(), None, None, predictor=predictor,
                           renderer=renderer, looks=several) if several is not None else None

    def iteration(mode):
        def run():
            s = simulate(variables())
            if mode == "render":
                renderer.set_look(nominal)
                pred = predictor.predict(renderer(s.float(), seed=0))[1]
            elif mode == "looks":  # risp-task --looks K: the tasks' own render loss, N's readings averaged over K looks
                looks_loss(s.float()).backward()
                return
            else:
                pred = env.state_to_target(s)
            ((pred.double() - goal.double()) ** 2).sum(-1).mean().backward()
        return run

    for fn in (sim_only, render_only, network_only):  # warm-up (kernel compilation)
        fn()
    out = {"simulation": _median_time(sim_only, repeats), "rendering": _median_time(render_only, repeats),
           "network": _median_time(network_only, repeats)}
    out["state"] = _median_time(iteration("state"), repeats)
    out["render"] = _median_time(iteration("render"), repeats)
    if several is not None:  # warm-up in the looks, then timed
        iteration("looks")()
        out["looks"] = _median_time(iteration("looks"), repeats)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--envs", default="quadrotor,cube,hand,rod")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--gradient", default="flat", help="boundary term: flat (risp's) or mitsuba")
    ap.add_argument("--looks", type=int, default=1, help="also time render mode reading this many looks (> 1)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"load average before: {os.getloadavg()}")
    print(f"{'env':10s} {'state s/it':>10s} {'render s/it':>11s}   shares of a render-mode iteration (sim / render / net)")
    for env in args.envs.split(","):
        r = bench_env(env, args.frames, args.res, args.spp, args.repeats, args.gradient, args.looks)
        parts = r["simulation"] + r["rendering"] + r["network"]
        print(f"{env:10s} {r['state']:10.3f} {r['render']:11.3f}   "
              f"{r['simulation'] / parts:5.0%} / {r['rendering'] / parts:5.0%} / {r['network'] / parts:5.0%}   "
              f"(sim {r['simulation']:.3f} s, render {r['rendering']:.3f} s, net {r['network']:.3f} s)"
              + (f"; --looks {args.looks}: {r['looks']:.3f} s/it ({r['looks'] / r['render']:.2f}× render)"
                 if "looks" in r else ""), flush=True)
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
