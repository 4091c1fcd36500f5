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
    """One differentiable rendering parameter in one domain: name ([a-z0-9_], no dots), nominal value,
    the range ψ is sampled from — ``intervals`` (a union of closed intervals), ``low``/``high`` their
    hull — what it means in that domain and its unit."""

    name: str
    nominal: float
    low: float
    high: float
    description: str
    unit: str = ""
    intervals: tuple[tuple[float, float], ...] = ()


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
# Training ranges (domain ``train``: ψ_j uniform in [low, high]).
OBJECT_RANGE = (0.1, 0.9)
FLOOR_RANGE = (0.2, 0.8)
LIGHT_RANGE = (0.5, 2.0)
AMBIENT_RANGE = (0.05, 0.5)
# Target domain: brighter light and ambient, colours *outside* the training ranges (each channel below
# or above, by at most the margin, clipped to the physical reflectances REFLECTANCE_CLIP).
TARGET_LIGHT_RANGE = (1.0, 3.0)
TARGET_AMBIENT_RANGE = (0.3, 0.8)
TARGET_OBJECT_MARGIN = 0.09
TARGET_FLOOR_MARGIN = 0.15
REFLECTANCE_CLIP = (0.01, 0.99)

# What each ψ is per domain, and its unit (the manifest's ``psi.descriptions`` and ``psi.units``).
_LIGHT_UNIT = ("dimensionless multiple of the nominal key light: 1 gives an irradiance of LIGHT_IRRADIANCE = 3 "
               "(linear image units) at the camera target, facing the light")
_DESCRIPTIONS = {
    "train": {
        "light_intensity": "key light strength, point light (1 = nominal irradiance at the target)",
        "ambient": "radiance of the constant grey environment",
        "object": "object reflectance (diffuse), {C} channel",
        "floor": "floor reflectance tint, {C} channel: reflectance = tint x texture colour",
    },
    "target": {
        "light_intensity": "key light strength, square area light tinted by aux light_color "
                           "(1 = nominal irradiance at the target)",
        "ambient": "scale of the procedural sky map (aux sky_zenith, sky_horizon) lighting the scene",
        "object": "object reflectance, {C} channel, of the diffuse base under a rough metal coat "
                  "(aux object_gloss, object_roughness)",
        "floor": "floor reflectance tint, {C} channel: reflectance = tint x texture colour (tiles or wood)",
    },
}
_UNITS = {
    "train": {"ambient": "radiance in the images' linear RGB units (the same units as the image pixels)"},
    "target": {"ambient": "dimensionless scale on the sky map's radiance (sky map values in linear image units)"},
}
_REFLECTANCE_UNIT = "dimensionless reflectance (albedo, fraction of light reflected) in [0, 1]"
_TINT_UNIT = "dimensionless factor on the floor texture's reflectance colours"


def _outside(low: float, high: float, margin: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """[low − margin, low] ∪ [high, high + margin], clipped to REFLECTANCE_CLIP."""
    return (max(low - margin, REFLECTANCE_CLIP[0]), low), (high, min(high + margin, REFLECTANCE_CLIP[1]))


def _check_env(env: str) -> None:
    """Unknown names raise the registry's RispError (risp_data.envs.ENV_NAMES is the one list of names)."""
    get_environment(env)


def _check_domain(domain: str) -> None:
    if domain not in DOMAINS:
        raise RispError(f"unknown domain {domain!r}; choose one of: {', '.join(DOMAINS)}")


def psi_specs(env: str, domain: str = "train") -> tuple[PsiSpec, ...]:
    """The K = 8 rendering parameters of ``env`` (same names and order in both domains) with the ranges,
    descriptions and units of ``domain``: ``train`` gives the training ranges; ``target`` the ranges
    :func:`sample_rendering` draws target-domain ψ from (outside the training ranges for colours)."""
    _check_env(env)
    _check_domain(domain)
    obj = _OBJECT_NOMINAL[env]
    text, target = _DESCRIPTIONS[domain], domain == "target"
    light = TARGET_LIGHT_RANGE if target else LIGHT_RANGE
    ambient = TARGET_AMBIENT_RANGE if target else AMBIENT_RANGE

    def spec(name, nominal, intervals, description, unit):
        intervals = tuple((float(a), float(b)) for a, b in intervals)
        return PsiSpec(name, nominal, min(a for a, _ in intervals), max(b for _, b in intervals), description,
                       unit, intervals)

    specs = [
        spec("light_intensity", 1.0, [light], text["light_intensity"], _LIGHT_UNIT),
        spec("ambient", 0.2, [ambient], text["ambient"], _UNITS[domain]["ambient"]),
    ]
    for c, ch in enumerate("rgb"):
        rng = _outside(*OBJECT_RANGE, TARGET_OBJECT_MARGIN) if target else [OBJECT_RANGE]
        specs.append(spec(f"object_{ch}", obj[c], rng, text["object"].format(C=ch.upper()), _REFLECTANCE_UNIT))
    for ch in "rgb":
        rng = _outside(*FLOOR_RANGE, TARGET_FLOOR_MARGIN) if target else [FLOOR_RANGE]
        specs.append(spec(f"floor_{ch}", 0.5, rng, text["floor"].format(C=ch.upper()), _TINT_UNIT))
    return tuple(specs)


JACOBIAN_MEANING = (
    "jacobian[j] = dI/dpsi_j, the derivative of the stored linear-RGB image with respect to the raw value of "
    "psi_j exactly as stored with the sample (psi.npy / zarr psi), in psi_j's unit (psi.units): no "
    "normalisation by the ranges, so J_j has image units per unit of psi_j")


def psi_manifest(env: str, domain: str) -> dict:
    """The manifest's ``psi`` block for a folder of ``domain``: names, nominal values, the ranges ψ is
    sampled from in that domain (``low``/``high`` hull and ``intervals``), the training ranges
    (``train_low``/``train_high``), descriptions and units, and what J is differentiated with respect to."""
    specs, train = psi_specs(env, domain), psi_specs(env, "train")
    sampling = ("uniform in [low, high]" if domain == "train" else
                "light_intensity, ambient: uniform in [low, high]; colours: each channel uniform in one of its "
                "two intervals (below or above the training range, chosen with probability 1/2)")
    return {
        "names": [s.name for s in specs],
        "nominal": [float(s.nominal) for s in specs],
        "domain": domain,
        "low": [float(s.low) for s in specs],
        "high": [float(s.high) for s in specs],
        "intervals": [[list(i) for i in s.intervals] for s in specs],
        "sampling": sampling,
        "train_low": [float(s.low) for s in train],
        "train_high": [float(s.high) for s in train],
        "descriptions": [s.description for s in specs],
        "units": [s.unit for s in specs],
        "jacobian": JACOBIAN_MEANING,
    }


def own_channels(env: str) -> dict[str, str]:
    """ψ whose ∂I/∂ψ_j lives in one colour channel only, and that channel: the material colours
    ``object_<c>`` and ``floor_<c>`` (each scales one channel of a reflectance, and the ``rgb`` variant never
    mixes channels).  Shards store only that channel where a sample shows it exact (risp_data.shards.layout)."""
    return {s.name: s.name[-1].upper() for s in psi_specs(env) if s.name.startswith(("object_", "floor_"))}


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
    """Values in [low − margin, low) ∪ (high, high + margin], clipped to REFLECTANCE_CLIP (reflectances)."""
    (a, b), (c, d) = _outside(low, high, margin)
    below = rng.uniform(a, b, size)
    above = rng.uniform(c, d, size)
    return np.where(rng.random(size) < 0.5, below, above)


def sample_rendering(env: str, domain: str, rng: np.random.Generator) -> RenderConfig:
    """Draw ψ and aux for one sample.

    ``train``: ψ_j uniform in [low_j, high_j]; light direction uniform in azimuth, elevation uniform in
    [30°, 75°], distance uniform in [3, 5] m from the camera target; floor texture uniform over
    TRAIN_FLOOR_TEXTURES with a random texture seed.
    ``target``: light intensity in TARGET_LIGHT_RANGE = [1, 3], ambient in TARGET_AMBIENT_RANGE = [0.3, 0.8],
    object and floor colours *outside* the training ranges (each channel below or above it; the intervals
    of ``psi_specs(env, "target")``), area light of side [0.5, 1.5] m with a warm/cool
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
        [rng.uniform(*TARGET_LIGHT_RANGE), rng.uniform(*TARGET_AMBIENT_RANGE)],
        _sample_outside(rng, *OBJECT_RANGE, TARGET_OBJECT_MARGIN, 3),
        _sample_outside(rng, *FLOOR_RANGE, TARGET_FLOOR_MARGIN, 3),
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
