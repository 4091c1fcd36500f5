"""How a trained network reads renders of fewer samples per pixel than its training images (docs/tasks.md
§Primal spp).

    PYTHONPATH=. python benchmarks/primal_spp_reading.py runs/rod-train-stochastic-s0/model.pt [--n 48] [--spp 2,4,8,16,64]

Renders ``--n`` states drawn from the environment's sampler (seed 7) in the train domain's nominal look — what
``risp-task … --loss render`` renders — with :class:`risp_data.diff_render.StateRenderer` at each ``--spp``, and
prints N's per-group error against the true states (risp_train.evaluate.group_errors: metres, degrees, radians)
and the mean and RMS shift of its raw target readings relative to the largest spp.  One thread each for torch and
Dr.Jit.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("--n", type=int, default=48)
    ap.add_argument("--spp", default="2,4,8,16,64")
    args = ap.parse_args()
    import drjit as dr
    import torch

    import risp_train
    from risp_data.diff_render import StateRenderer
    from risp_data.envs import get_environment
    from risp_train.evaluate import group_errors

    torch.set_num_threads(1)
    dr.set_thread_count(1)
    predictor = risp_train.load(args.model)
    env = get_environment(predictor.env_name)
    states = np.asarray(env.sample_states(np.random.default_rng(np.random.SeedSequence([7, 7])), args.n), np.float64)
    spps = [int(s) for s in args.spp.split(",")]
    readings = {}
    print(f"{predictor.env_name}: {args.n} states, nominal look, {predictor.resolution}×{predictor.resolution}; "
          f"the network's training images: {predictor.spp or 'unrecorded'} spp")
    for spp in spps:
        renderer = StateRenderer(predictor.env_name, resolution=predictor.resolution, spp=spp)
        t0 = time.perf_counter()
        with torch.no_grad():
            images = torch.cat([renderer(torch.tensor(s[None], dtype=torch.float32), seed=100 + i)
                                for i, s in enumerate(states)])
            pred, targets = predictor.predict(images)
        groups = group_errors(predictor.env_name, pred.double().numpy(), states)
        readings[spp] = targets.double().numpy()
        summary = ", ".join(f"{k} {np.mean(v):.4g} ± {np.std(v):.3g}" for k, v in groups.items())
        print(f"spp {spp:4d}: {summary}   ({time.perf_counter() - t0:.1f} s)")
    ref = max(spps)
    for spp in spps:
        if spp == ref:
            continue
        d = readings[spp] - readings[ref]
        print(f"readings at spp {spp} − spp {ref}: mean {np.array2string(d.mean(0), precision=4)}, "
              f"RMS {np.array2string(np.sqrt((d ** 2).mean(0)), precision=4)}")


if __name__ == "__main__":
    main()
