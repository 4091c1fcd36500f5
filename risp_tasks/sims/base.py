"""The simulator interface shared by all tasks (system identification, control, diagnose).

Brax-style: a state in, a state out, no hidden globals; physical parameters are a plain tensor input.

Shapes (B = batch, P = parameters, X = full simulator state, A = action dimension, T = steps):

    params  (B, P)     ordered as ``sim.param_names`` (base parameters, then each enabled effect's)
    state   (B, X)     ordered as ``sim.state_names``
    actions (B, T, A)  or None when ``sim.action_dim == 0``
    rollout(params, s0, actions, steps) -> (B, steps + 1, X), row 0 is s0

float32 and float64 both work; gradients flow to params, s0 and actions.  ``to_env_state`` maps full
simulator states (..., X) onto the risp_data environment's state vector (..., S) so that simulated
trajectories can be rendered.  Equations, units and defaults: docs/models.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from risp_data.errors import RispError


@dataclass(frozen=True)
class Effect:
    """A named extra physical effect (off by default) with its own parameters."""

    name: str
    param_names: tuple[str, ...]
    defaults: tuple[float, ...]  # a typical non-zero magnitude
    ranges: tuple[tuple[float, float], ...]  # plausible physical range of each parameter
    description: str = ""
    # Validity: closed interval [lo, hi] per parameter checked by ``check_inputs`` (None: any finite value).
    bounds: tuple[tuple[float, float], ...] | None = None
    units: tuple[str, ...] | None = None
    # Extra state entries the effect appends to the full state (e.g. motor_lag's thrust states).
    state_names: tuple[str, ...] = ()


@dataclass(frozen=True)
class SimulatorSpec:
    """What every simulator declares; concrete simulators subclass :class:`Simulator`."""

    env: str
    dt: float
    state_names: tuple[str, ...]
    base_param_names: tuple[str, ...]
    base_param_defaults: tuple[float, ...]
    action_dim: int
    available_effects: dict[str, Effect] = field(default_factory=dict)
    # Validity interval [lo, hi] of each base parameter (None: any finite value) and plausible ranges.
    base_param_bounds: tuple[tuple[float, float], ...] | None = None
    base_param_ranges: tuple[tuple[float, float], ...] | None = None
    base_param_units: tuple[str, ...] | None = None


class Simulator:
    """Base class. Subclasses implement :meth:`step` and :meth:`to_env_state` and set ``spec``."""

    spec: SimulatorSpec

    def __init__(self, effects: tuple[str, ...] | list[str] = ()):
        unknown = [e for e in effects if e not in self.spec.available_effects]
        if unknown:
            raise RispError(
                f"unknown effect(s) {', '.join(unknown)} for {self.spec.env}; "
                f"choose from: {', '.join(self.spec.available_effects) or 'none'}"
            )
        self.effects: tuple[str, ...] = tuple(effects)

    # -- layout -----------------------------------------------------------------------------------
    @property
    def env(self) -> str:
        return self.spec.env

    @property
    def dt(self) -> float:
        return self.spec.dt

    @property
    def state_names(self) -> tuple[str, ...]:
        """Base state entries, then the extra entries of each enabled effect (in ``effects`` order)."""
        names = self.spec.state_names
        for e in self.effects:
            names += self.spec.available_effects[e].state_names
        return names

    @property
    def action_dim(self) -> int:
        return self.spec.action_dim

    @property
    def param_names(self) -> tuple[str, ...]:
        names = list(self.spec.base_param_names)
        for e in self.effects:
            names += [f"{e}.{p}" for p in self.spec.available_effects[e].param_names]
        return tuple(names)

    def default_params(self, batch: int = 1, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        vals = list(self.spec.base_param_defaults)
        for e in self.effects:
            vals += list(self.spec.available_effects[e].defaults)
        return torch.tensor(vals, dtype=dtype).expand(batch, -1).clone()

    @property
    def param_bounds(self) -> tuple[tuple[float, float], ...]:
        """Validity interval [lo, hi] of every parameter, ordered as ``param_names``."""
        inf = float("inf")
        n = len(self.spec.base_param_names)
        bounds = list(self.spec.base_param_bounds or ((-inf, inf),) * n)
        for e in self.effects:
            eff = self.spec.available_effects[e]
            bounds += list(eff.bounds or ((-inf, inf),) * len(eff.param_names))
        return tuple(bounds)

    def default_state(self, batch: int = 1, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """A typical initial state (batch, X); simulators that have one override this."""
        raise NotImplementedError(f"the {self.env} simulator defines no default state")

    def check_state(self, s0: torch.Tensor) -> None:
        """Hook for simulator-specific checks of the initial state (e.g. a non-zero quaternion)."""

    def param_index(self, name: str) -> int:
        try:
            return self.param_names.index(name)
        except ValueError:
            raise RispError(f"unknown parameter {name!r}; parameters are: {', '.join(self.param_names)}") from None

    def effect_params(self, params: torch.Tensor, name: str) -> torch.Tensor | None:
        """(B, n) columns of effect ``name``'s parameters in ``params`` (B, P), or None when the effect is off."""
        if name not in self.effects:
            return None
        names = self.spec.available_effects[name].param_names
        i = self.param_index(f"{name}.{names[0]}")
        return params[:, i:i + len(names)]

    # -- dynamics -----------------------------------------------------------------------------------
    def step(self, params: torch.Tensor, state: torch.Tensor, action: torch.Tensor | None, t: int) -> torch.Tensor:
        raise NotImplementedError

    def to_env_state(self, states: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def check_full_states(self, states) -> None:
        """One clear error unless ``states`` is a tensor of full simulator states (..., X)."""
        if not torch.is_tensor(states) or states.shape[-1] != len(self.state_names):
            shape = tuple(states.shape) if torch.is_tensor(states) else type(states).__name__
            raise RispError(f"states must have shape (..., {len(self.state_names)}), got {shape}")

    def check_param_bounds(self, params: torch.Tensor, option: str = "") -> None:
        """One clear error for a parameter outside its physical bounds (a negative mass, a friction above 1);
        ``option`` prefixes the message with where the value came from (``--params: ``)."""
        for i, (lo, hi) in enumerate(self.param_bounds):
            col = params[:, i]
            outside = ~((col >= lo) & (col <= hi))  # written so that NaN (every comparison false) is outside too
            if bool(outside.any()):
                bad = col[outside][0].item()
                where = f"{option}{self.param_names[i]}" if option else f"params[:, {i}] ({self.param_names[i]})"
                raise RispError(f"{where} must lie in [{lo:g}, {hi:g}], got {bad:g}")

    def check_inputs(self, params, s0, actions, steps) -> None:
        """Clear errors naming the argument for wrong shapes, NaNs and out-of-range values."""
        if not isinstance(steps, int) or steps < 0:
            raise RispError(f"steps must be a non-negative int, got {steps!r}")
        if not torch.is_tensor(params) or params.ndim != 2 or params.shape[1] != len(self.param_names):
            shape = tuple(params.shape) if torch.is_tensor(params) else type(params).__name__
            raise RispError(f"params must have shape (B, {len(self.param_names)}) ({', '.join(self.param_names)}), got {shape}")
        if not torch.is_tensor(s0) or s0.ndim != 2 or s0.shape[1] != len(self.state_names):
            shape = tuple(s0.shape) if torch.is_tensor(s0) else type(s0).__name__
            raise RispError(f"s0 must have shape (B, {len(self.state_names)}), got {shape}")
        if s0.shape[0] != params.shape[0]:
            raise RispError(f"params and s0 disagree on the batch size ({params.shape[0]} vs {s0.shape[0]})")
        if not torch.isfinite(params).all():
            bad = [self.param_names[i] for i in torch.nonzero(~torch.isfinite(params).all(0)).flatten().tolist()]
            raise RispError(f"params contain NaN/inf in: {', '.join(bad)}")
        if not torch.isfinite(s0).all():
            raise RispError("s0 contains NaN/inf")
        if not params.is_floating_point() or s0.dtype != params.dtype:
            raise RispError(f"params and s0 must share one floating dtype, got {params.dtype} and {s0.dtype}")
        self.check_param_bounds(params)
        self.check_state(s0)
        if self.action_dim == 0:
            if actions is not None:
                raise RispError(f"{self.env} takes no actions; pass actions=None")
        else:
            if actions is None or not torch.is_tensor(actions) or actions.ndim != 3 or actions.shape[0] != s0.shape[0] \
                    or actions.shape[1] < steps or actions.shape[2] != self.action_dim:
                shape = tuple(actions.shape) if torch.is_tensor(actions) else actions
                raise RispError(f"actions must have shape (B={s0.shape[0]}, T>={steps}, {self.action_dim}), got {shape}")
            if not torch.isfinite(actions).all():
                raise RispError("actions contain NaN/inf")
            if actions.dtype != params.dtype:
                raise RispError(f"actions must have the dtype of params ({params.dtype}), got {actions.dtype}")

    def rollout(self, params: torch.Tensor, s0: torch.Tensor, actions: torch.Tensor | None, steps: int) -> torch.Tensor:
        """Integrate ``steps`` steps; returns (B, steps + 1, X) with row 0 = s0."""
        self.check_inputs(params, s0, actions, steps)
        states = [s0]
        s = s0
        for t in range(steps):
            a = None if actions is None else actions[:, t]
            s = self.step(params, s, a, t)
            states.append(s)
        return torch.stack(states, 1)
