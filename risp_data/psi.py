"""Rendering parameters ψ (issue 2, item 3): per environment K = 8 differentiable scalars, plus a
JSON-serialisable dict of non-differentiable randomisation, in two domains.

ψ (same names, order and meaning in both domains, so shards have one layout):

====================  =================================================================================
``light_intensity``   key light strength, relative: 1 gives an irradiance of LIGHT_IRRADIANCE at the
                      camera target whatever the light's distance (point light in ``train``, area light
                      in ``target``).
``ambient``           radiance of the environment (constant grey in ``train``; a scale on a procedural
                      sky map in ``target``).
``object_r/g/b``      reflectance of the object material (diffuse in ``train``; the diffuse base under
                      a rough metal coat in ``target``).
``floor_r/g/b``       tint of the floor: floor reflectance = tint · texture(aux), per RGB channel.
====================  =================================================================================

Domains: ``train`` samples ψ uniformly in each spec's [low, high]; ``target`` is a deliberately
different look for reference videos (docs/rendering.md): another integrator and sample count, an area
light and an environment map, a textured floor, glossy objects and colours outside the training ranges.
Every scene parameter is a *linear* function of ψ (risp_data.render), so ∂I/∂ψ_j is well defined in both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .envs import get_environment
from .errors import RispError

DOMAINS: tuple[str, ...] = ("train", "target")
TRAIN_FLOOR_TEXTURES: tuple[str, ...] = ("plain", "checker", "noise")
TARGET_FLOOR_TEXTURES: tuple[str, ...] = ("tiles", "wood")


@dataclass(frozen=True)
class PsiSpec:
    """One differentiable rendering parameter: name ([a-z0-9_], no dots), nominal value, training range."""

    name: str
    nominal: float
    low: float
    high: float
    description: str


@dataclass(frozen=True)
class RenderConfig:
    """ψ (K,) float64 in the order of :func:`psi_specs`, and the non-differentiable randomisation."""

    psi: np.ndarray
    aux: dict = field(default_factory=dict)


# Nominal object colours per environment (all inside the training range [0.1, 0.9]).
_OBJECT_NOMINAL = {
    "quadrotor": (0.25, 0.35, 0.70),
    "cube": (0.75, 0.30, 0.20),
    "hand": (0.80, 0.60, 0.50),
    "rod": (0.30, 0.60, 0.30),
}
OBJECT_RANGE = (0.1, 0.9)
FLOOR_RANGE = (0.2, 0.8)
LIGHT_RANGE = (0.5, 2.0)
AMBIENT_RANGE = (0.05, 0.5)


def _check_env(env: str) -> None:
    """Unknown names raise the registry's RispError (risp_data.envs.ENV_NAMES is the one list of names)."""
    get_environment(env)


def _check_domain(domain: str) -> None:
    if domain not in DOMAINS:
        raise RispError(f"unknown domain {domain!r}; choose one of: {', '.join(DOMAINS)}")


def psi_specs(env: str) -> tuple[PsiSpec, ...]:
    """The K = 8 rendering parameters of ``env`` (training ranges; same names in both domains)."""
    _check_env(env)
    obj = _OBJECT_NOMINAL[env]
    specs = [
        PsiSpec("light_intensity", 1.0, *LIGHT_RANGE, "key light strength (1 = nominal irradiance at the target)"),
        PsiSpec("ambient", 0.2, *AMBIENT_RANGE, "environment radiance (grey)"),
    ]
    for c, ch in enumerate("rgb"):
        specs.append(PsiSpec(f"object_{ch}", obj[c], *OBJECT_RANGE, f"object reflectance, {ch.upper()} channel"))
    for ch in "rgb":
        specs.append(PsiSpec(f"floor_{ch}", 0.5, *FLOOR_RANGE, f"floor reflectance tint, {ch.upper()} channel"))
    return tuple(specs)


def psi_names(env: str) -> tuple[str, ...]:
    return tuple(s.name for s in psi_specs(env))


def _direction(azimuth: float, elevation: float) -> list[float]:
    ce = math.cos(elevation)
    return [ce * math.cos(azimuth), ce * math.sin(azimuth), math.sin(elevation)]


def nominal_rendering(env: str, domain: str = "train") -> RenderConfig:
    """ψ at the nominal values; fixed aux (light up-left-front of the scene, plain/tiled floor)."""
    _check_env(env)
    _check_domain(domain)
    psi = np.array([s.nominal for s in psi_specs(env)], np.float64)
    if domain == "train":
        aux = {"light_direction": _direction(-2.0, math.radians(55)), "light_distance": 4.0,
               "floor_texture": "plain", "texture_seed": 0}
    else:
        aux = {"light_direction": _direction(-2.0, math.radians(55)), "light_distance": 4.0, "light_size": 1.0,
               "light_color": [1.0, 0.92, 0.8], "floor_texture": "tiles", "texture_seed": 0,
               "object_roughness": 0.15, "object_gloss": 0.25,
               "sky_zenith": [0.35, 0.5, 0.9], "sky_horizon": [0.9, 0.85, 0.75]}
    return RenderConfig(psi=psi, aux=aux)


def _sample_outside(rng: np.random.Generator, low: float, high: float, margin: float, size: int) -> np.ndarray:
    """Values in [low − margin, low) ∪ (high, high + margin], clipped to [0.01, 0.99] (reflectances)."""
    below = rng.uniform(max(low - margin, 0.01), low, size)
    above = rng.uniform(high, min(high + margin, 0.99), size)
    return np.where(rng.random(size) < 0.5, below, above)


def sample_rendering(env: str, domain: str, rng: np.random.Generator) -> RenderConfig:
    """Draw ψ and aux for one sample.

    ``train``: ψ_j uniform in [low_j, high_j]; light direction uniform in azimuth, elevation uniform in
    [30°, 75°], distance uniform in [3, 5] m from the camera target; floor texture uniform over
    TRAIN_FLOOR_TEXTURES with a random texture seed.
    ``target``: light intensity in [1, 3], ambient in [0.3, 0.8], object and floor colours *outside* the
    training ranges (each channel below or above it), area light of side [0.5, 1.5] m with a warm/cool
    tint, a procedural sky, tiled or wood floor, glossy objects (blend weight of a rough metal coat in
    [0.15, 0.4], GGX roughness in [0.05, 0.3]).
    """
    _check_env(env)
    _check_domain(domain)
    if not isinstance(rng, np.random.Generator):
        raise RispError("rng must be a numpy.random.Generator (seeds are explicit)")
    specs = psi_specs(env)
    direction = _direction(float(rng.uniform(0, 2 * math.pi)), float(math.radians(rng.uniform(30, 75))))
    distance = float(rng.uniform(3.0, 5.0))
    seed = int(rng.integers(0, 2**31 - 1))
    if domain == "train":
        psi = np.array([rng.uniform(s.low, s.high) for s in specs], np.float64)
        aux = {"light_direction": direction, "light_distance": distance,
               "floor_texture": str(TRAIN_FLOOR_TEXTURES[rng.integers(len(TRAIN_FLOOR_TEXTURES))]),
               "texture_seed": seed}
        return RenderConfig(psi=psi, aux=aux)
    psi = np.concatenate([
        [rng.uniform(1.0, 3.0), rng.uniform(0.3, 0.8)],
        _sample_outside(rng, *OBJECT_RANGE, 0.09, 3),
        _sample_outside(rng, *FLOOR_RANGE, 0.15, 3),
    ]).astype(np.float64)
    warm = float(rng.uniform(-1, 1))
    aux = {"light_direction": direction, "light_distance": distance,
           "light_size": float(rng.uniform(0.5, 1.5)),
           "light_color": [1.0, 1.0 - 0.15 * max(warm, 0) , 1.0 - 0.3 * max(warm, 0) + 0.2 * min(warm, 0)],
           "floor_texture": str(TARGET_FLOOR_TEXTURES[rng.integers(len(TARGET_FLOOR_TEXTURES))]),
           "texture_seed": seed, "object_roughness": float(rng.uniform(0.05, 0.3)),
           "object_gloss": float(rng.uniform(0.15, 0.4)),
           "sky_zenith": rng.uniform([0.2, 0.3, 0.6], [0.4, 0.6, 1.0]).tolist(),
           "sky_horizon": rng.uniform([0.7, 0.6, 0.5], [1.0, 0.9, 0.8]).tolist()}
    return RenderConfig(psi=psi, aux=aux)
