"""Candidate models: the base model and the base model extended by the simulator's named effects.

Which parameters are free (fitted) and which are fixed (from the sidecar) is decided here
(docs/diagnose.md §Models):

* base parameters named in the sidecar (mass, side, inertia, …) are fixed to the sidecar's values;
* base parameters listed in :data:`BASE_FREE` for the environment are fitted in every model;
* each switched-on effect's parameters are fitted, starting from the effect's typical magnitude and kept
  inside its plausible range.

Candidates are every single effect and pairs of the best singles (:func:`pair_candidates`).
"""

from __future__ import annotations

import importlib
import itertools
import math

import torch

from risp_data.errors import RispError
from risp_tasks.sims import available_effects, get_simulator

from ..measured import Sidecar
from .adapter import matched_simulator
from .fit import DTYPE, Model

CUBE_MAX_SUBSTEP = 0.7e-3  # s
#: Largest quadrotor step [s]: the semi-implicit Euler step's one-sample error must stay well below the
#: measurement noise (at 10 ms the base model left ρ = 1.3 on effect-free data, at 2 ms ρ ≈ 1).
QUAD_MAX_STEP = 2e-3
#: The quadrotor library's force-like effect ranges are for the simulator's nominal 3 kg vehicle; for
#: another vehicle they scale with its weight, and the wind force's plausible range is ±WIND_WEIGHT_FRACTION·m·g.
QUAD_NOMINAL_MASS = 3.0
WIND_WEIGHT_FRACTION = 0.5

#: Base-model parameters fitted in every model (when the simulator has them), per environment.
#: Everything else in the base model is either given by the sidecar or kept at the simulator default.
BASE_FREE: dict[str, tuple[str, ...]] = {
    "cube": ("log10_kn", "dn"),  # contact stiffness and damping: not in the sidecar, not an "effect"
    "quadrotor": (),
    "hand": (),
    "rod": (),
}

#: Sidecar keys -> simulator parameter names, where they differ; list values name one parameter per
#: element (inertia diagonal).
SIDECAR_PARAM_NAMES: dict[str, dict[str, object]] = {
    "cube": {"side": ("side", "cube_side", "size"), "mass": ("mass",), "gravity": ("gravity", "g")},
    "quadrotor": {
        "mass": ("mass",),
        "gravity": ("gravity", "g"),
        "arm_length": ("arm_length", "arm"),
        "yaw_torque_coefficient": ("k_m", "yaw_torque_coefficient", "k_yaw", "km"),
        "inertia": (("Ixx", "Iyy", "Izz"), ("inertia_x", "inertia_y", "inertia_z"), ("Jxx", "Jyy", "Jzz"),
                    ("inertia.xx", "inertia.yy", "inertia.zz"), ("Ix", "Iy", "Iz")),
    },
    "hand": {},
    "rod": {},
}


def fixed_values(sim, sidecar: Sidecar) -> dict[str, float]:
    """Simulator parameter name -> value taken from the sidecar."""
    out: dict[str, float] = {}
    names = set(sim.param_names)
    for key, cands in SIDECAR_PARAM_NAMES.get(sim.env, {}).items():
        if key not in sidecar.values:
            continue
        val = sidecar.values[key]
        if isinstance(val, (list, tuple)):
            for group in cands:
                if isinstance(group, tuple) and len(group) == len(val) and all(n in names for n in group):
                    out.update({n: float(v) for n, v in zip(group, val)})
                    break
        else:
            for n in cands:
                if isinstance(n, str) and n in names:
                    out[n] = float(val)
                    break
    # any other scalar sidecar key that is literally a simulator parameter name
    for key, val in sidecar.values.items():
        if key in names and isinstance(val, (int, float)) and not isinstance(val, bool):
            out.setdefault(key, float(val))
    return out


def check_supported(env: str, sidecar: Sidecar) -> None:
    """Sidecar values the simulator cannot represent (it has them as fixed constants) stop the run."""
    if env == "rod":
        from risp_tasks.sims.rod import GRAVITY
    elif env in ("quadrotor", "cube"):
        from risp_tasks.sims._rigid import GRAVITY
    else:  # the hand's base model has no gravity (its `gravity` effect is a candidate): nothing fixed to check
        return

    g = sidecar.get("gravity")
    if g is not None and abs(float(g) - GRAVITY) > 0.01:
        raise RispError(f"{sidecar.source}: gravity {g} differs from the simulator's fixed {GRAVITY} m/s²")


def make_sim(env: str, effects: tuple[str, ...], sidecar: Sidecar, sample_dt: float):
    """The simulator with ``effects``, its step matched to the sampling interval; returns (sim, k).

    k = round(Δ / dt_native) simulator steps per sample with dt = Δ / k, passed as the simulators' ``dt``
    option (cube: also ``side`` and ``mass`` from the sidecar).  Simulators without options go through
    the registry and :func:`matched_simulator`.
    """
    module = importlib.import_module(f"risp_tasks.sims.{env}")
    native = float(module.SPEC.dt)
    k = max(1, int(round(sample_dt / native)))
    if env == "quadrotor":
        k = max(k, math.ceil(sample_dt / QUAD_MAX_STEP - 1e-9))
    options = {"dt": sample_dt / k}
    if env == "quadrotor" and translational(sidecar):
        options["mode"] = "translational"
    elif env == "quadrotor":
        options.update(quadrotor_geometry(sidecar))
        if str(sidecar.get("thrust_map", "linear")).lower() == "quadratic":
            options["thrust_quadratic"] = True
    if env == "cube":
        # substeps of at most CUBE_MAX_SUBSTEP: the light real cube (0.37 kg, k_n = 1e6) with friction
        # blows up at the simulator's default 5 ms substep (measured: speeds of 10³ m/s within 0.6 s)
        sub = max(int(getattr(module, "SUBSTEPS", 1)), math.ceil(sample_dt / k / CUBE_MAX_SUBSTEP - 1e-9))
        options.update(side=float(sidecar.get("side")), mass=float(sidecar.get("mass")), substeps=sub)
    try:
        sim = module.make_simulator(tuple(effects), **options)
    except TypeError:
        sim, k = matched_simulator(get_simulator(env, effects), sample_dt)
    return sim, k


def translational(sidecar: Sidecar) -> bool:
    """Collective-thrust logs are diagnosed with the translational quadrotor model (attitude from the data)."""
    return sidecar.env == "quadrotor" and str(sidecar.get("actuator", "thrust")).lower().startswith("collective")


def quadrotor_geometry(sidecar: Sidecar) -> dict:
    """Simulator options from the sidecar: arm_length, rotor_layout ("+"/"x") or rotor_angles_deg, rotor_spin."""
    out = {}
    if sidecar.get("arm_length") is not None:
        out["arm_length"] = float(sidecar.get("arm_length"))
    if sidecar.get("rotor_angles_deg") is not None:
        out["rotor_angles"] = tuple(math.radians(float(a)) for a in sidecar.get("rotor_angles_deg"))
    elif sidecar.get("rotor_layout") is not None:
        out["layout"] = str(sidecar.get("rotor_layout")).lower()
    if sidecar.get("rotor_spin") is not None:
        out["spin"] = tuple(float(x) for x in sidecar.get("rotor_spin"))
    return out


def scaled_range(env: str, effect: str, lo: float, hi: float, sidecar: Sidecar) -> tuple[float, float]:
    """An effect parameter's plausible range for this vehicle (docs/diagnose.md §2): quadrotor force-like
    ranges scale with the weight; the wind force is ±WIND_WEIGHT_FRACTION·m·g."""
    if env != "quadrotor" or sidecar.get("mass") is None:
        return lo, hi
    m = float(sidecar.get("mass"))
    if effect == "wind":
        w = WIND_WEIGHT_FRACTION * m * 9.81
        return -w, w
    if effect in ("rotor_drag", "air_drag"):
        return lo * m / QUAD_NOMINAL_MASS, hi * m / QUAD_NOMINAL_MASS
    return lo, hi


def build_model(env: str, effects: tuple[str, ...], sidecar: Sidecar, sample_dt: float) -> tuple[Model, int]:
    """The model with ``effects`` switched on; returns (model, sub-steps per sample)."""
    sim, k = make_sim(env, effects, sidecar, sample_dt)
    base = sim.default_params(1, DTYPE)[0].clone()
    for name, v in fixed_values(sim, sidecar).items():
        base[sim.param_index(name)] = v
    inf = float("inf")
    bounds = dict(zip(sim.param_names, getattr(sim, "param_bounds", ((-inf, inf),) * len(sim.param_names))))
    base_ranges = dict(zip(sim.spec.base_param_names, getattr(sim.spec, "base_param_ranges", None) or ()))
    free = [n for n in BASE_FREE.get(env, ()) if n in sim.param_names]
    scale, lower, upper, plausible = [], [], [], []
    actuator = str(sidecar.get("actuator", "thrust")).lower()
    if env == "quadrotor" and actuator in ("normalized", "pwm", "collective_normalized"):
        # normalised commands: the thrust map f = k_f·u is fitted, starting from hover m·g = n·k_f·u_hover
        # (n = 4 rotor commands, or 1 collective throttle)
        n_cmd = 1 if actuator == "collective_normalized" else 4
        k_f0 = float(base[sim.param_index("mass")]) * 9.81 / (n_cmd * float(sidecar.get("hover_throttle")))
        base[sim.param_index("k_f")] = k_f0
        free.append("k_f")
        scale.append(0.25 * k_f0)
        lower.append(0.25 * k_f0)
        upper.append(4.0 * k_f0)
        if "k_f2" in sim.param_names:  # quadratic thrust map f = k_f·u + k_f2·u², k_f2 from 0
            base[sim.param_index("k_f2")] = 0.0
            free.append("k_f2")
            scale.append(0.25 * k_f0)
            lower.append(-k_f0)
            upper.append(k_f0)
    for n in free[len(scale):]:
        if n in base_ranges:
            lo, hi = map(float, base_ranges[n])
            width = hi - lo
            scale.append(max(width / 4.0, 1e-12))
            lower.append(max(lo - width, float(bounds[n][0])))
            upper.append(min(hi + width, float(bounds[n][1])))
        else:
            v = abs(float(base[sim.param_index(n)])) or 1.0
            scale.append(0.5 * v)
            lower.append(float(bounds[n][0]))
            upper.append(float(bounds[n][1]))
    spec = sim.spec.available_effects
    for e in effects:
        eff = spec[e]
        for p, (lo, hi) in zip(eff.param_names, eff.ranges):
            lo, hi = scaled_range(env, e, float(lo), float(hi), sidecar)
            name = f"{e}.{p}"
            free.append(name)
            plausible.append((float(lo), float(hi)))
            width = float(hi) - float(lo)
            scale.append(max(width / 4.0, 1e-12))
            # the plausible range widened by its width on each side, inside the simulator's validity bounds
            blo, bhi = bounds[name]
            # a range starting at zero stays non-negative (simulators reject negative magnitudes)
            wlo = float(lo) - width if float(lo) < 0 else max(float(lo) - width, 0.0) if float(lo) > 0 else 0.0
            lower.append(max(wlo, float(blo)))
            upper.append(min(float(hi) + width, float(bhi)))
    t = lambda v: torch.tensor(v, dtype=DTYPE)  # noqa: E731
    plausible = [None] * (len(free) - len(plausible)) + plausible  # base parameters come first
    model = Model(sim=sim, base=base, free=tuple(free), scale=t(scale), lower=t(lower), upper=t(upper),
                  effects=tuple(effects), plausible=tuple(plausible))
    return model, k


def effect_names(env: str, sidecar: Sidecar | None = None) -> tuple[str, ...]:
    """The candidate library: the simulator's effects (the translational quadrotor model has its own)."""
    if sidecar is not None and translational(sidecar):
        from risp_tasks.sims.quadrotor import TRANSLATIONAL_EFFECTS

        return TRANSLATIONAL_EFFECTS
    return tuple(available_effects(env))


def pair_candidates(ranked_singles: list[str], top: int = 3) -> list[tuple[str, str]]:
    """Pairs among the ``top`` best single effects (by held-out score)."""
    return list(itertools.combinations(ranked_singles[:top], 2))
