"""Experiment: does averaging several trained networks (a deep ensemble) read target-domain images better than
one network?  Per state group (metres, degrees), one network at a time, every pair, and all of them averaged.
The networks' raw targets (position, sin/cos pairs) are averaged before the map to states.

    python benchmarks/ensemble_eval.py --models 'tables-cpu/runs/quadrotor-*/model.pt' \\
        --shards 'tables-cpu/data/quadrotor-test-r*'

docs/RESULTS.md §Averaging networks records the answer for the quadrotor (no: the error is the look's, common to
every network trained on the same data).
"""

from __future__ import annotations

import argparse
import glob
import itertools

import numpy as np
import torch


def main() -> None:
    from risp_data.envs import get_environment
    from risp_train.checkpoint import load_checkpoint
    from risp_train.data import iter_batches, open_shards
    from risp_train.evaluate import summarize_groups
    from risp_train.predictor import predictor_from_checkpoint

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", required=True, help="glob of model.pt files (one environment)")
    ap.add_argument("--shards", required=True, help="glob of shard folders to evaluate on")
    args = ap.parse_args()
    torch.set_num_threads(1)
    models, sets = sorted(glob.glob(args.models)), sorted(glob.glob(args.shards))
    if len(models) < 2 or not sets:
        raise SystemExit(f"need two or more models and one or more shard folders; found {len(models)}, {len(sets)}")
    nets = {m: predictor_from_checkpoint(load_checkpoint(m), m) for m in models}
    env = get_environment(nets[models[0]].env_name)
    images, true = [], []
    for folder in sets:
        for batch in iter_batches(open_shards(folder, "auto"), 64, state_dim=env.state_dim):
            images.append(batch["image"])
            true.append(batch["state"].numpy())
    images, true = torch.cat(images), np.concatenate(true)
    with torch.no_grad():
        targets = {m: net.predict(images)[1].double() for m, net in nets.items()}

    def groups(t: torch.Tensor) -> str:
        g = summarize_groups(env.name, env.target_to_state(t).numpy(), true)
        return "  ".join(f"{k} {v['mean']:.4g}" for k, v in g.items())

    print(f"{env.name}, {len(true)} images from {len(sets)} shard folders")
    for m in models:
        print(f"one  {m}: {groups(targets[m])}")
    for a, b in itertools.combinations(models, 2):
        print(f"pair {a} + {b}: {groups((targets[a] + targets[b]) / 2)}")
    print(f"all {len(models)}: {groups(torch.stack([targets[m] for m in models]).mean(0))}")


if __name__ == "__main__":
    main()
