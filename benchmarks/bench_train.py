"""Training-step cost of the four regularizers (issue 5 benchmark).

    python benchmarks/bench_train.py            # 64×64, batch 16, K = the env's ψ count, ResNet-18 width 64
    python benchmarks/bench_train.py --quick    # fewer rounds
    python benchmarks/bench_train.py --shards shards/cube   # use the first batch of real shards as input
    python benchmarks/bench_train.py --width 16 --stem imagenet   # another stem than the automatic one

One optimizer step = input normalization + chain rule of J, loss (regularizers.py), backward, Adam step,
exactly as in train.py.  Methods are timed interleaved (none, surrogate, exact, stochastic, none, …) in
one process and summarized by medians, because timings on a shared machine drift between runs.
Without --shards the inputs are random positive images and random J of the right shapes: the cost of a
step does not depend on pixel values.  Targets: surrogate ≤ 2.5×, stochastic ≤ 2.5×, exact ≤ (1 + K)×.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="cube")
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--rounds", type=int, default=None, help="timed rounds (7; --quick 3)")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--stem", default="auto", help="auto (model.stem_for_resolution), imagenet, stride2 or small")
    ap.add_argument("--shards", default=None)
    ap.add_argument("--quick", action="store_true", help="3 rounds")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    rounds = args.rounds or (3 if args.quick else 7)  # an explicit --rounds wins over --quick

    from risp_data.envs import get_environment
    from risp_data.psi import psi_names
    from risp_train.model import ModelConfig, build_model, stem_for_resolution
    from risp_train.normalization import StatsAccumulator
    from risp_train.regularizers import REGULARIZERS, risp_loss
    from risp_train.train import batch_tensors, step_generator

    env = get_environment(args.env)
    k = len(psi_names(args.env))
    if args.shards:
        from risp_train.data import iter_batches, open_shards

        shards = open_shards(args.shards)
        batch = next(iter_batches(shards, args.batch, need_jacobian=True, state_dim=env.state_dim))
        args.res, k = shards.resolution, len(shards.psi_names)
        source = f"first {args.batch} samples of {args.shards}"
    else:
        g = torch.Generator().manual_seed(0)
        b, r = args.batch, args.res
        batch = {"image": torch.rand(b, r, r, 3, generator=g) * 0.8,
                 "jacobian": torch.randn(b, k, r, r, 3, generator=g) * 0.1,
                 "state": torch.as_tensor(env.sample_states(__import__("numpy").random.default_rng(0), b))}
        source = "random images and J (timing does not depend on pixel values)"
    acc = StatsAccumulator(env.target_dim)
    acc.add(batch["image"], env.state_to_target(batch["state"]))
    norm = acc.result()
    stem = stem_for_resolution(args.res) if args.stem == "auto" else args.stem
    net = build_model(ModelConfig(out_dim=env.target_dim, width=args.width, stem=stem), 0)
    opt = torch.optim.Adam(net.parameters(), lr=1e-4, weight_decay=1e-6)

    def step(reg: str, i: int) -> float:
        t0 = time.perf_counter()
        x, y, tangents = batch_tensors(batch, norm, env, reg != "none")
        terms = risp_loss(net, x, y, reg, 1.0, tangents, step_generator(0, 0, i))
        opt.zero_grad(set_to_none=True)
        terms.total.backward()
        opt.step()
        return time.perf_counter() - t0

    print(f"env {args.env}: {args.res}×{args.res}, batch {args.batch}, K = {k}, ResNet-18 width {args.width}, stem {stem}, "
          f"{torch.get_num_threads()} threads, inputs: {source}")
    for reg in REGULARIZERS:  # warm-up (allocator, functorch dispatch caches)
        step(reg, 0)
    times: dict[str, list[float]] = {reg: [] for reg in REGULARIZERS}
    for i in range(rounds):
        for reg in REGULARIZERS:
            times[reg].append(step(reg, i + 1))
    base = statistics.median(times["none"])
    limits = {"none": 1.0, "surrogate": 2.5, "exact": 1.0 + k, "stochastic": 2.5}
    print(f"{'method':<11} {'median ms':>10} {'ratio':>7} {'images/s':>9} {'target':>8}")
    for reg in REGULARIZERS:
        med = statistics.median(times[reg])
        ratio = med / base
        ok = "" if reg == "none" else ("ok" if ratio <= limits[reg] else "MISSED")
        print(f"{reg:<11} {1e3 * med:>10.1f} {ratio:>6.2f}× {args.batch / med:>9.1f} {'≤' + format(limits[reg], 'g') + '× ' + ok if reg != 'none' else '':>8}")
    print(f"({rounds} interleaved rounds; medians)")


if __name__ == "__main__":
    main()
