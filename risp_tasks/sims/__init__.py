"""Differentiable simulators, one module per environment, behind one registry.

    >>> from risp_tasks.sims import get_simulator
    >>> sim = get_simulator("cube", effects=("friction",))
    >>> states = sim.rollout(sim.default_params(), s0, None, steps=100)
"""

from __future__ import annotations

import importlib

from risp_data.envs import ENV_NAMES
from risp_data.errors import RispError

from .base import Effect, Simulator, SimulatorSpec


def get_simulator(env: str, effects: tuple[str, ...] | list[str] = (), **options) -> Simulator:
    """The simulator of environment ``env`` with the named extra effects switched on.

    ``options`` go to the environment's constructor (e.g. ``side``, ``mass``, ``dt``, ``substeps`` for the
    cube; see docs/models.md); an option the simulator does not take raises :class:`RispError`.
    """
    if env not in ENV_NAMES:
        raise RispError(f"unknown environment {env!r}; choose one of: {', '.join(ENV_NAMES)}")
    module = importlib.import_module(f"{__name__}.{env}")
    try:
        return module.make_simulator(tuple(effects), **options)
    except TypeError as e:
        if options and "argument" in str(e):
            raise RispError(f"{env} simulator does not take option(s) {', '.join(options)}: {e}") from None
        raise


def available_effects(env: str) -> dict[str, Effect]:
    if env not in ENV_NAMES:
        raise RispError(f"unknown environment {env!r}; choose one of: {', '.join(ENV_NAMES)}")
    module = importlib.import_module(f"{__name__}.{env}")
    return dict(module.SPEC.available_effects)


#: how far k whole steps of a simulator's fixed step may miss an interval (a video frame, a measured sample): beyond it
#: the simulated clock drifts from the data's (a 2 % slack let 7–14 fps videos drift 1–2 %)
STEP_TOLERANCE = 2e-3


def whole_steps(sim, interval: float) -> int | None:
    """k = round(interval / dt) when k ≥ 1 steps of ``sim``'s step span ``interval`` within STEP_TOLERANCE, else None."""
    k = int(round(interval / sim.dt))
    return k if k >= 1 and abs(k * sim.dt - interval) <= STEP_TOLERANCE * interval else None


def step_rates(sim) -> str:
    """The rates [1/s] whose interval is a whole number of ``sim``'s steps (1, 2, 3, 4, 5, 10 steps), for errors."""
    return ", ".join(f"{1.0 / (j * sim.dt):.4g}" for j in (1, 2, 3, 4, 5, 10))


__all__ = ["Effect", "STEP_TOLERANCE", "Simulator", "SimulatorSpec", "available_effects", "get_simulator", "step_rates",
           "whole_steps"]
