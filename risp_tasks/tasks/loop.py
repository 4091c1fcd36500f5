"""The one optimisation loop of every task, and the loss modes (docs/tasks.md §Losses).

    L_render(θ)    = mean_t ‖N(R(s_t(θ))) − N(I_t)‖²   the paper's loss (target space of the network); with
                     ``--looks K`` > 1 N(R(·)) is replaced by (1/K) Σ_k N(R_k(·)), N's readings of the frame rendered in
                     K random train-domain looks ψ_1…ψ_K averaged (docs/tasks.md §Several looks)
    L_state(θ)     = mean_t ‖τ(s_t(θ)) − N(I_t)‖²      no rendering in the loop (the paper's real-world pipeline)
    L_oracle(θ)    = mean_t ‖τ(s_t(θ)) − τ(s*_t)‖²     ground-truth states (evaluation only)
    L_pixelwise(θ) = mean over t, pixels, channels of (R(s_t(θ)) − I_t)²   ∇Sim's image loss (a baseline)
    L_perceptual(θ) = mean over t and features of (F(R(s_t(θ))) − F(I_t))²   a feature loss (a baseline; F:
                      risp_tasks.tasks.features)

With ``--grow-horizon G`` the sums run over the first n(i) compared frames at iteration i (a horizon curriculum,
:func:`horizon`), n(i) = min(T, 2 + ⌊(T − 2)·i / G⌋) for i < G and T afterwards.

With ``--residual l1`` the three losses in the network's target space (render, state, oracle) sum absolute instead
of squared differences, mean_t ‖·‖₁: the least-absolute-deviations fit, robust to the network's occasional large
misreadings (its errors are heavy-tailed; docs/tasks.md §Residual norm).  The image losses stay squared.

s_t(θ): the simulated environment state at kept frame t; τ: the environment's state → network-target map
(x, y, z, sin/cos of angles, …); N: the frozen network; R: the differentiable renderer in the train domain's
nominal look; I_t: the reference frames at the network's resolution.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field
from typing import Callable

import torch

from risp_data.errors import RispError

from .config import RESIDUALS


class Timer:
    """Wall seconds per named section, summed over the run."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    @contextlib.contextmanager
    def section(self, name: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start


@dataclass
class Problem:
    """What a task optimises: leaf tensors (normalised coordinates) and how they become frame states."""

    variables: dict[str, torch.Tensor]
    states: Callable[[], torch.Tensor]  # -> (n_source_frames, S) environment states, differentiable
    estimates: Callable[[], dict]  # current estimates in physical units (JSON-able)
    project: Callable[[], None] = lambda: None  # keep variables feasible after a step (e.g. clamp to [0, 1])
    frames: list[int] | None = None  # which source frames the loss compares (None: the reference's kept frames)
    info: dict = field(default_factory=dict)


def make_loss(mode: str, env, keep: list[int], ref_targets: torch.Tensor | None, truth_targets: torch.Tensor | None,
              ref_images: torch.Tensor | None, predictor=None, renderer=None, timer: Timer | None = None,
              features=None, residual: str = "l2", render_seed: int = 0, looks: list | None = None
              ) -> Callable[..., torch.Tensor]:
    """loss(states (n_source, S), n=None) -> scalar for one of the modes above, on the frames ``keep`` (only their
    first ``n`` when given: the horizon curriculum); ``features``: F of the perceptual mode (a frozen torch module,
    images (B, H, W, 3) -> (B, D)); ``residual``: ``l2`` (squared) or ``l1`` (absolute) differences in the
    network's target space (render, state, oracle); ``render_seed``: the sampler seed of every render (the run's
    --seed); ``looks``: the render loss's looks (RenderConfigs) whose readings are averaged (None: the renderer's
    own look alone)."""
    timer = timer or Timer()
    if looks is not None and mode != "render":
        raise RispError(f"several looks are for the render loss (N's readings averaged over the looks), not the "
                        f"{mode} loss")
    if looks is not None and not looks:
        raise RispError("looks is empty: give at least one look, or None for the renderer's own")
    if residual not in RESIDUALS:
        raise RispError(f"unknown residual {residual!r}; choose one of: {', '.join(RESIDUALS)}")

    def target_error(pred_targets, goal):
        r = pred_targets - goal
        return (r.abs() if residual == "l1" else r ** 2).sum(-1).mean()

    def first(n):  # the compared frames' indices and the slice of the per-frame references that goes with them
        n = len(keep) if n is None else n
        return keep[:n], slice(0, n)

    if mode == "state":
        def state_loss(s, n=None):
            idx, sl = first(n)
            return target_error(env.state_to_target(s[idx]), ref_targets[sl].to(s.dtype))
        return state_loss
    if mode == "oracle":
        if truth_targets is None:
            raise RispError("--loss oracle needs ground-truth states (--truth)")

        def oracle_loss(s, n=None):
            idx, sl = first(n)
            return target_error(env.state_to_target(s[idx]), truth_targets[sl].to(s.dtype))
        return oracle_loss
    # Every render of one descent uses the same sampler seed (common random numbers): the image loss is then a
    # deterministic function of the state, so iterates — and the best-iterate rule — are compared on the same noise.
    # The seed is the run's, so that repeats with different --seed see independent render noise.
    if mode == "render":
        def read(states):  # N(R(s)), in the renderer's current look
            with timer.section("rendering"):
                images = renderer(states, seed=render_seed)
            with timer.section("network"):
                return predictor.predict(images)[1]

        def render_loss(s, n=None):
            idx, sl = first(n)
            if looks is None:
                targets = read(s[idx])
            else:  # (1/K) Σ_k N(R_k(s)); each frame's backward pass runs in its own look (StateRenderer)
                readings = []
                for look in looks:
                    renderer.set_look(look)
                    readings.append(read(s[idx]))
                targets = torch.stack(readings).mean(0)
            return target_error(targets.to(s.dtype), ref_targets[sl].to(s.dtype))
        return render_loss
    if mode == "pixelwise":
        def pixel_loss(s, n=None):
            idx, sl = first(n)
            with timer.section("rendering"):
                images = renderer(s[idx], seed=render_seed)
            return ((images - ref_images[sl]) ** 2).mean().to(s.dtype)
        return pixel_loss
    if mode == "perceptual":
        with torch.no_grad():
            goal = features(ref_images)  # F(I_t), once

        def perceptual_loss(s, n=None):
            idx, sl = first(n)
            with timer.section("rendering"):
                images = renderer(s[idx], seed=render_seed)
            with timer.section("network"):
                f = features(images)
            return ((f - goal[sl]) ** 2).mean().to(s.dtype)
        return perceptual_loss
    raise RispError(f"unknown loss {mode!r}")


def horizon(iteration: int, grow: int, frames: int) -> int:
    """Compared frames at ``iteration`` of a horizon curriculum over ``grow`` iterations
    (docs/tasks.md §Horizon curriculum): n(i) = min(T, 2 + ⌊(T − 2)·i / G⌋) for i < G, T afterwards
    (T = ``frames``, G = ``grow``; G = 0: always T).

    Why: an open-loop rollout that starts a little wrong can leave what the early frames show (the quadrotor
    flies out of the camera's view), and an image loss is flat there.  Fitting the first frames first keeps the
    descent where the loss has a gradient, and each extension starts from a rollout that already follows them."""
    if iteration >= grow or frames <= 2:
        return frames
    return min(frames, 2 + (frames - 2) * iteration // grow)


def make_optimizer(name: str, params, lr: float, momentum: float) -> torch.optim.Optimizer:
    if name == "rmsprop":
        return torch.optim.RMSprop(params, lr=lr, momentum=momentum)
    if name == "adam":
        return torch.optim.Adam(params, lr=lr)
    return torch.optim.SGD(params, lr=lr, momentum=momentum)


def optimize(problem: Problem, loss: Callable, *, optimizer: str, lr: float, momentum: float, iterations: int,
             timer: Timer, progress: bool = True, grow: int = 0, frames: int | None = None,
             opt: torch.optim.Optimizer | None = None) -> dict:
    """Minimise ``loss(problem.states())`` over ``problem.variables``; returns the per-iteration history.

    The variables are left at the *best* iterate by the task's own loss, not the last: with a fixed step size a
    long, chaotic rollout (the quadrotor's open-loop flights) can overshoot in a late step, and a user asking for
    the parameters that best explain the video wants the ones that did.  ``final_loss`` is that iterate's loss,
    ``last_loss`` the last iterate's, ``best_iteration`` its index (``iterations`` = the point after the last
    step).  The selection uses only the optimised loss, never ground truth.

    ``opt``: an optimiser over ``problem.variables`` to continue (its step sizes and momentum as a previous call
    left them: the warm start, docs/tasks.md §Warm start); by default a fresh one from ``optimizer``, ``lr`` and
    ``momentum``.  The history's ``optimizer`` is the one used (None without variables or iterations), to continue.

    A non-finite loss (a step into NaN) stops the descent there: the best iterate so far is kept, ``stopped``
    says where, ``last_loss`` is NaN and ``optimizer`` None; a non-finite loss before any iterate could be kept is
    an error.

    ``grow`` > 0 (with ``frames``, the number of compared frames T): the horizon curriculum — iteration i compares
    the first :func:`horizon` (i, grow, T) frames; only full-horizon iterates compete for the best, and
    ``frames_compared`` records n(i) per iteration, ``frames_in_loss`` T.
    """
    from tqdm import tqdm

    leaves = list(problem.variables.values())
    if opt is None and leaves and iterations:
        opt = make_optimizer(optimizer, leaves, lr, momentum)
    history, seconds = [], []
    best_value, best_iteration, best_leaves = float("inf"), iterations, None
    stopped = None
    if grow and frames is None:
        raise RispError("a horizon curriculum needs the number of compared frames")
    compared = []
    bar = tqdm(range(iterations), desc="optimizing", unit="it", disable=not progress, leave=False)
    for it in bar:
        start = time.perf_counter()
        opt.zero_grad()
        with timer.section("simulation"):
            states = problem.states()
        n = horizon(it, grow, frames) if grow else None
        value = loss(states) if n is None else loss(states, n)
        if not torch.isfinite(value):
            if best_leaves is None:  # nothing comparable to keep yet: the start itself is non-finite
                if it == 0:  # no step was taken: the inputs themselves simulate to NaN/inf, --lr cannot help
                    raise RispError("the loss is NaN/inf at the start, before any optimisation step: the simulation "
                                    "of the inputs diverges (check --actions, --params and the initial state)")
                raise RispError(f"the loss became NaN/inf at iteration {it}, before any iterate could be kept "
                                "(try a smaller --lr)")
            # a long run should not be thrown away by one bad step: stop here, keep the best iterate so far
            stopped = (f"the loss became NaN/inf at iteration {it}; the optimisation stopped there and kept its "
                       f"best iterate ({best_iteration}; try a smaller --lr)")
            break
        history.append(float(value.detach()))
        compared.append(n)
        # only full-horizon losses compete; keep the variables that gave this loss, before the step moves them
        if (n is None or n == frames) and history[-1] < best_value:
            best_value, best_iteration = history[-1], it
            best_leaves = [v.detach().clone() for v in leaves]
        with timer.section("backward"):
            value.backward()
        opt.step()
        with torch.no_grad():
            problem.project()
        seconds.append(time.perf_counter() - start)
        bar.set_postfix(loss=f"{history[-1]:.4g}")
    with torch.no_grad():
        last = float("nan") if stopped else float(loss(problem.states()))
    final = last
    if best_leaves is not None and not last <= best_value:  # NaN-safe: a non-finite last loss is never kept
        with torch.no_grad():
            for v, b in zip(leaves, best_leaves):
                v.copy_(b)
        final = best_value
    else:
        best_iteration = iterations
    out = {"loss": history, "final_loss": final, "last_loss": last, "best_iteration": best_iteration,
           "seconds_per_iteration": seconds, "optimizer": None if stopped else opt}
    if stopped:  # its optimiser state may hold the non-finite step: not handed on (a warm start's next phase)
        out["stopped"] = stopped
    if grow:
        out["frames_compared"], out["frames_in_loss"] = compared, frames
    return out
