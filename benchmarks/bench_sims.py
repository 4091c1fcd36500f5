"""Forward + backward time of a 100-step rollout per simulator, batch 1 and 64 (issue 3 targets).

    python benchmarks/bench_sims.py            # every environment in the registry, 7 repeats
    python benchmarks/bench_sims.py --quick    # 20 steps, 3 repeats
    python benchmarks/bench_sims.py --env cube --effects friction,restitution --threads 1

Prints, per environment and batch size, the median wall time of rollout + backward (float32, gradients
w.r.t. params, s0 and actions) and the ratio batch-64 / batch-1.  Environments are run interleaved so
that the drift of a shared machine hits all alike.  Targets at batch 1 (100 steps): quadrotor ≤ 50 ms,
hand ≤ 100 ms, cube ≤ 200 ms, rod ≤ 3 s.
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import time

import torch

from risp_data.envs import ENV_NAMES
from risp_tasks.sims import get_simulator

TARGET_MS = {"quadrotor": 50.0, "hand": 100.0, "cube": 200.0, "rod": 3000.0}


def _inputs(sim, batch: int, steps: int, gen: torch.Generator):
    dtype = torch.float32
    params = sim.default_params(batch, dtype)
    try:
        s0 = sim.default_state(batch, dtype)
    except NotImplementedError:
        s0 = torch.zeros(batch, len(sim.state_names), dtype=dtype)
    actions = None
    if sim.action_dim:
        actions = 0.1 * torch.rand(batch, steps, sim.action_dim, generator=gen, dtype=dtype)
        if sim.env == "quadrotor":
            actions = actions + sim.hover_actions(params, steps)
    return params, s0, actions


def time_once(sim, batch: int, steps: int, gen: torch.Generator) -> float:
    params, s0, actions = _inputs(sim, batch, steps, gen)
    leaves = [params.requires_grad_(), s0.requires_grad_()] + ([actions.requires_grad_()] if actions is not None else [])
    t0 = time.perf_counter()
    states = sim.rollout(params, s0, actions, steps)
    torch.autograd.grad(states.pow(2).sum(), leaves, allow_unused=True)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="20 steps, 3 repeats")
    ap.add_argument("--env", default=None, help="one environment (default: all with a simulator module)")
    ap.add_argument("--effects", default="", help="comma-separated effects to switch on (with --env)")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    steps = args.steps or (20 if args.quick else 100)
    repeats = args.repeats or (3 if args.quick else 7)

    envs = [args.env] if args.env else list(ENV_NAMES)
    sims = {}
    for env in envs:
        try:
            importlib.import_module(f"risp_tasks.sims.{env}")
        except ModuleNotFoundError:
            print(f"{env}: no simulator module, skipped")
            continue
        effects = tuple(e for e in args.effects.split(",") if e) if args.env else ()
        sims[env] = get_simulator(env, effects)

    gen = torch.Generator().manual_seed(args.seed)
    times = {(env, b): [] for env in sims for b in (1, 64)}
    for env, sim in sims.items():  # warm-up (first calls allocate and build caches)
        time_once(sim, 1, min(steps, 5), gen)
    for _ in range(repeats):
        for env, sim in sims.items():
            for b in (1, 64):
                times[env, b].append(time_once(sim, b, steps, gen))

    print(f"forward+backward of a {steps}-step rollout, float32, median of {repeats} "
          f"(torch threads: {torch.get_num_threads()})")
    print(f"{'env':<10} {'effects':<28} {'batch 1 [ms]':>13} {'batch 64 [ms]':>14} {'64/1':>6} {'target@1 [ms]':>14}")
    for env, sim in sims.items():
        t1 = statistics.median(times[env, 1]) * 1e3
        t64 = statistics.median(times[env, 64]) * 1e3
        target = TARGET_MS.get(env, float("nan")) * steps / 100
        print(f"{env:<10} {','.join(sim.effects) or '-':<28} {t1:>13.1f} {t64:>14.1f} {t64 / t1:>6.2f} {target:>14.0f}")


if __name__ == "__main__":
    main()
