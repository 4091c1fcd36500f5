"""How large the regularizer's parameter gradient is next to the state error's (docs/RESULTS.md §Identifiable
marks, revisited): for a few training batches, ‖∇θ R‖ / ‖∇θ ℓ‖ with R the calibrated stochastic regularizer
(risp_train.regularizers) and ℓ the mean state error, at a checkpoint's initial weights (its seed) or its
trained weights.

    python benchmarks/reg_gradient_ratio.py runs/cube-train-stochastic-s0/model.pt shards/cube-train [--trained]

A ratio of 30–100 at initialization means that even γ = 0.01 makes R's (noisy, v-sampled) gradient as large
as the state error's in the early steps, where Adam's second-moment estimates are formed.
"""

from __future__ import annotations

import argparse
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from risp_data.envs import get_environment  # noqa: E402
from risp_train.checkpoint import load_checkpoint  # noqa: E402
from risp_train.data import iter_batches, open_shards  # noqa: E402
from risp_train.model import ModelConfig, build_model  # noqa: E402
from risp_train.normalization import Normalization  # noqa: E402
from risp_train.regularizers import calibrated_regularizer, psi_scale  # noqa: E402
from risp_train.train import batch_tensors  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("shards", help="training shards with Jacobians")
    ap.add_argument("--trained", action="store_true", help="the checkpoint's weights (default: its initial ones)")
    ap.add_argument("--batches", type=int, default=6)
    ap.add_argument("--batch-size", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0, help="seed of the stochastic regularizer's v draws")
    args = ap.parse_args()
    torch.set_num_threads(1)
    ck = load_checkpoint(args.checkpoint)
    net = build_model(ModelConfig.from_dict(ck["model_config"]), int(ck.get("seed", 0)))
    if args.trained:
        net.load_state_dict(ck["model"])
    norm = Normalization.from_dict(ck["normalization"])
    shards = open_shards(args.shards)
    env = get_environment(shards.env)
    scale = psi_scale(shards.env).view(1, -1, 1, 1, 1)
    generator = torch.Generator().manual_seed(args.seed)
    params = list(net.parameters())
    print("| batch | state error | R | ‖∇ error‖ | ‖∇ R‖ | ratio |\n|---:|---:|---:|---:|---:|---:|")
    for i, batch in enumerate(iter_batches(shards, args.batch_size, need_jacobian=True, state_dim=env.state_dim)):
        if i == args.batches:
            break
        x, y, tangents = batch_tensors(batch, norm, env, True, None)
        tangents = tangents * scale.to(tangents)
        v = torch.randn(x.shape[0], tangents.shape[1], generator=generator, dtype=x.dtype)
        err, r = calibrated_regularizer(net, x, y, "stochastic", tangents, v)
        g_err = torch.autograd.grad(err.mean(), params, retain_graph=True, allow_unused=True)
        g_r = torch.autograd.grad(r, params, allow_unused=True)
        n_err = float(torch.sqrt(sum((g ** 2).sum() for g in g_err if g is not None)))
        n_r = float(torch.sqrt(sum((g ** 2).sum() for g in g_r if g is not None)))
        print(f"| {i} | {float(err.mean().detach()):.3f} | {float(r.detach()):.3f} | {n_err:.3g} | {n_r:.3g} | {n_r / n_err:.1f} |")


if __name__ == "__main__":
    main()
