"""Mitsuba renderer with forward-mode Jacobian stacks (issue 2, item 4; docs/rendering.md).

One :class:`Renderer` per (environment, domain, resolution, spp, variant).  The Mitsuba scene is built
once; each sample only rewrites vertex positions and the ψ-dependent scene parameters in place.

Jacobian J_j = ∂I/∂ψ_j (forward mode, no finite differences).  Every ψ-dependent scene parameter p_k is a
*linear* function of ψ, p_k = P_k(ψ; aux), so its tangent along ψ_j is P_k(e_j; aux).  One sample runs

    1. one primal pass of the path-replay integrator (rays and sampler state shared by all passes),
    2. K tangent passes: set the tangents of the scene parameters to P_k(e_j), replay the same paths
       in ``dr.ADMode.Forward`` (the integrator's forward mode, as in ``render_forward``, but with the
       primal computed once instead of once per tangent) and splat δL into J_j.

Same (state, config, seed) → same image and J (see docs/rendering.md for the measured tolerance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable

import numpy as np

from .envs import Environment, get_environment
from .envs.materials import FIXED_MATERIALS  # RGB reflectances of the non-ψ materials
from .errors import RispError
from .prb_passes import forward_materials, sample_per_emitter
from .mitsuba_setup import init_mitsuba
from .psi import RenderConfig, _check_domain, psi_specs

LIGHT_IRRADIANCE = 3.0  # W/m² at the camera target for light_intensity = 1 (facing the light)
TARGET_SPP_FACTOR = 4  # the target domain renders with 4× the requested samples per pixel
TEXTURE_SIZE = 64  # floor texture resolution (pixels per repeat)
FLOOR_HALF_SIZE = 10.0  # m, the floor rectangle spans [−10, 10]²
TEXTURE_REPEATS = 10  # the floor texture repeats 10× across the floor (2 m per repeat)
SKY_SIZE = (32, 64)  # target-domain environment map (rows, columns)


@dataclass(frozen=True)
class DomainSettings:
    """Integrator per domain.  Both use Mitsuba's path-replay integrator ``prb`` because the shared-primal
    forward mode needs an integrator whose ``sample`` runs in ``dr.ADMode.Forward`` from a stored primal
    state (``prbvolpath`` refuses forward mode; the C++ ``path`` has no separate primal/tangent passes);
    the target domain differs in path length and sample count.  No Russian roulette in either: its
    decisions depend on ψ, which would make same-seed finite differences (the Jacobian check) jump.

    Images rendered *without* a Jacobian in the target domain (reference videos, evaluation shards) use
    ``reference``: Mitsuba's C++ unidirectional path tracer ``path`` with Russian roulette, a different
    integrator with the same expected image (:meth:`Renderer.render_reference`)."""

    integrator: str
    max_depth: int
    rr_depth: int
    spp_factor: int
    reference: str | None = None  # integrator of Jacobian-free images (None: the same as ``integrator``)


DOMAIN_SETTINGS = {
    "train": DomainSettings("prb", 3, 5, 1),  # direct light + one indirect bounce, no roulette
    "target": DomainSettings("prb", 6, 6, TARGET_SPP_FACTOR, reference="path"),  # longer paths, 4× spp
}


# ----------------------------------------------------------------------------------------------------
# Procedural textures (numpy; deterministic in (name, seed))
# ----------------------------------------------------------------------------------------------------


@lru_cache(maxsize=64)
def floor_texture(name: str, seed: int, size: int = TEXTURE_SIZE) -> tuple[np.ndarray, tuple, tuple]:
    """A floor pattern: weight w (size, size) float32 in [0, 1] and two colours c0, c1.

    The floor reflectance is tint ⊙ ((1 − w) c0 + w c1) with tint = (floor_r, floor_g, floor_b) — a
    blend of two diffuse BSDFs whose reflectances tint ⊙ c0 and tint ⊙ c1 are linear in ψ (the pattern
    itself is not differentiated).  Deterministic in (name, seed).
    """
    rng = np.random.default_rng(int(seed))
    y, x = np.mgrid[0:size, 0:size] / size
    grey = ((1.0, 1.0, 1.0), (0.5, 0.5, 0.5))
    if name == "plain":
        return np.zeros((size, size), np.float32), *grey
    if name == "checker":
        cells = int(rng.choice([4, 8]))
        w = ((np.floor(x * cells) + np.floor(y * cells)) % 2).astype(np.float64)
        return w.astype(np.float32), *grey
    if name == "noise":  # smooth value noise: bilinear upsampling of an 8×8 random grid
        grid = rng.uniform(0.0, 1.0, (9, 9))
        gx, gy = x * 8, y * 8
        ix, iy = np.floor(gx).astype(int), np.floor(gy).astype(int)
        fx, fy = gx - ix, gy - iy
        w = (grid[iy, ix] * (1 - fx) * (1 - fy) + grid[iy, ix + 1] * fx * (1 - fy)
             + grid[iy + 1, ix] * (1 - fx) * fy + grid[iy + 1, ix + 1] * fx * fy)
        return w.astype(np.float32), *grey
    if name == "tiles":  # cream and terracotta tiles with dark grout
        cells = 4
        w = 0.45 * ((np.floor(x * cells) + np.floor(y * cells)) % 2) + rng.uniform(0, 0.1)
        grout = np.minimum((x * cells) % 1, (y * cells) % 1) < 0.06
        return np.where(grout, 1.0, w).astype(np.float32), (0.95, 0.9, 0.8), (0.12, 0.1, 0.09)
    if name == "wood":
        return _wood(rng, x, y), (1.0, 0.78, 0.52), (0.55, 0.33, 0.18)
    raise RispError(f"unknown floor texture {name!r} in the render config")


WOOD_PLANKS = 4  # planks per texture repeat (along y)


def _wood(rng: np.random.Generator, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Seamless wood planks on the unit square: w(x + 1, y) = w(x, y + 1) = w(x, y).

    Each of WOOD_PLANKS planks (along x) has grain stripes w = ½ + ½ sin(2π (g·v + A sin(2π(x + φ)) +
    B sin(2π(2x + v + φ')))), v = WOOD_PLANKS·y − plank index ∈ [0, 1), with integer g and per-plank random
    phases: every term has an integer frequency in x, so the texture tiles in x; the planks' boundaries
    (dark joints) fall on y = k / WOOD_PLANKS including y = 0 ≡ 1, so it tiles in y too.  The old ring
    pattern sqrt((x − 0.3)² · 0.2 + (y − 0.5)²) had a visible seam at every 2 m repeat (issue 9).
    """
    plank = np.floor(y * WOOD_PLANKS).astype(int) % WOOD_PLANKS
    v = y * WOOD_PLANKS - np.floor(y * WOOD_PLANKS)
    grains = rng.integers(3, 6, WOOD_PLANKS)[plank]
    phase, phase2 = rng.uniform(0, 1, (2, WOOD_PLANKS))
    shade = rng.uniform(-0.15, 0.15, WOOD_PLANKS)[plank]
    w = 0.5 + 0.5 * np.sin(2 * np.pi * (grains * v + 0.35 * np.sin(2 * np.pi * (x + phase[plank]))
                                        + 0.1 * np.sin(2 * np.pi * (2 * x + v + phase2[plank]))))
    joint = np.minimum(v, 1 - v) * WOOD_PLANKS < 0.04  # dark joint between planks
    return np.clip(np.where(joint, 1.0, 0.85 * w + shade + 0.075), 0, 1).astype(np.float32)


def sky_map(zenith, horizon, rows: int = SKY_SIZE[0], cols: int = SKY_SIZE[1]) -> np.ndarray:
    """(rows, cols, 3) latitude gradient from ``zenith`` (top) to ``horizon`` and a dim ground."""
    v = (np.arange(rows) + 0.5) / rows  # 0 = zenith, 1 = nadir
    up = np.clip(1 - 2 * v, 0, 1)[:, None] ** 0.5
    col = up * np.asarray(zenith) + (1 - up) * np.asarray(horizon)
    col = np.where((v < 0.5)[:, None], col, 0.3 * np.asarray(horizon))
    return np.repeat(col[:, None, :], cols, 1).astype(np.float32)


# ----------------------------------------------------------------------------------------------------
# The renderer
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Binding:
    """A scene parameter ``key`` that is a linear function ``value(ψ, aux)`` of ψ (numpy array)."""

    key: str
    value: Callable[[np.ndarray, dict], np.ndarray]
    kind: str  # "color" (Color3f) or "float" (Float)
    emitter: bool = False  # the radiance/intensity of an emitter (the image is linear in it)


class Renderer:
    """Render images and Jacobian stacks J = [∂I/∂ψ_1 … ∂I/∂ψ_K] of one environment in one domain."""

    def __init__(self, env: str | Environment, domain: str = "train", resolution: int = 64, spp: int = 16,
                 variant: str | None = None, jacobian_path: str = "fast"):
        # a name, or an Environment object (e.g. the quadrotor with a vehicle mesh from a file)
        self.env = env if isinstance(env, Environment) else get_environment(env)
        _check_domain(domain)
        if jacobian_path not in JACOBIAN_PATHS:
            raise RispError(f"unknown Jacobian path {jacobian_path!r}; choose one of: {', '.join(JACOBIAN_PATHS)}")
        self.jacobian_path = jacobian_path
        if not isinstance(resolution, (int, np.integer)) or resolution < 1:
            raise RispError(f"resolution must be a positive integer, got {resolution!r}")
        if not isinstance(spp, (int, np.integer)) or spp < 1:
            raise RispError(f"spp must be a positive integer, got {spp!r}")
        self.domain = domain
        self.resolution = int(resolution)
        self.spp = int(spp)
        self.settings = DOMAIN_SETTINGS[domain]
        self.variant = init_mitsuba(variant)
        self.specs = psi_specs(self.env.name)
        self.psi_names: tuple[str, ...] = tuple(s.name for s in self.specs)
        import drjit as dr
        import mitsuba as mi

        self._mi, self._dr = mi, dr
        self._build_scene()

    # -- scene construction (once) --------------------------------------------------------------------

    def _build_scene(self) -> None:
        mi = self._mi
        cam = self.env.camera
        target = self.domain == "target"
        nominal_state = (np.asarray(self.env.state_low) + np.asarray(self.env.state_high)) / 2
        parts = self._merged_meshes(nominal_state)
        bsdfs = {"object": self._object_bsdf()}
        for name, rgb in FIXED_MATERIALS.items():
            bsdfs[name] = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": list(rgb)}})
        scene: dict = {
            "type": "scene",
            "integrator": {"type": self.settings.integrator, "max_depth": self.settings.max_depth,
                           "rr_depth": self.settings.rr_depth},
            "sensor": {
                "type": "perspective",
                "fov": cam.fov,
                "fov_axis": "x",
                "to_world": mi.ScalarTransform4f().look_at(origin=cam.origin, target=cam.target, up=cam.up),
                "film": {"type": "hdrfilm", "width": self.resolution, "height": self.resolution,
                         "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                "sampler": {"type": "independent", "sample_count": self.spp * self.settings.spp_factor},
            },
            "floor": {
                "type": "rectangle",
                "to_world": mi.ScalarTransform4f().translate([0, 0, self.env.floor_height or 0.0])
                @ mi.ScalarTransform4f().scale([FLOOR_HALF_SIZE, FLOOR_HALF_SIZE, 1]),
                "bsdf": {"type": "blendbsdf",
                         "weight": {"type": "bitmap", "raw": True, "wrap_mode": "repeat",
                                    "bitmap": mi.Bitmap(np.zeros((TEXTURE_SIZE, TEXTURE_SIZE, 1), np.float32)),
                                    "to_uv": mi.ScalarTransform3f().scale([TEXTURE_REPEATS, TEXTURE_REPEATS])},
                         "bsdf_0": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5] * 3}},
                         "bsdf_1": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.4] * 3}}},
            },
        }
        if target:
            scene["light"] = {"type": "rectangle",
                              "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}
            scene["ambient"] = {"type": "envmap", "bitmap": mi.Bitmap(sky_map([0.3, 0.5, 0.9], [0.9, 0.85, 0.75])),
                                "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], 90)}
        else:
            scene["light"] = {"type": "point", "position": [0, 0, 3], "intensity": {"type": "rgb", "value": 1.0}}
            scene["ambient"] = {"type": "constant", "radiance": {"type": "rgb", "value": 0.2}}
        self._mesh_keys = {}
        for material, (verts, faces) in parts.items():
            props = mi.Properties()
            props["bsdf"] = bsdfs[material]
            mesh = mi.Mesh(f"mesh_{material}", verts.shape[0], faces.shape[0], has_vertex_normals=False,
                           has_vertex_texcoords=False, props=props)
            mp = mi.traverse(mesh)
            mp["vertex_positions"] = mi.Float(verts.astype(np.float32).ravel())
            mp["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
            mp.update()
            scene[f"mesh_{material}"] = mesh
            self._mesh_keys[material] = f"mesh_{material}.vertex_positions"
        self.scene = mi.load_dict(scene)
        self.params = mi.traverse(self.scene)
        self.integrator = self.scene.integrator()
        self.reference_integrator = None
        if self.settings.reference is not None:
            self.reference_integrator = mi.load_dict({"type": self.settings.reference,
                                                      "max_depth": self.settings.max_depth, "rr_depth": 3})
        self._bindings = self._make_bindings()
        self._emitters = {k: self._emitter_named(b.key.split(".")[0]) for k, b in enumerate(self._bindings)
                          if b.emitter}  # the Mitsuba emitter object each emitter binding sets
        self._texture_key, self._sky_key = None, None  # what the floor pattern / sky currently hold
        self._diff_keys = [b.key for b in self._bindings]
        missing = [k for k in self._diff_keys + list(self._mesh_keys.values()) if k not in self.params]
        if missing:  # a Mitsuba version with other parameter names: a programming error, not user input
            raise RuntimeError(f"scene parameters not found: {missing}")

    def _emitter_named(self, name: str):
        """The emitter of scene object ``name``: an emitter with that id, or the area emitter of a shape."""
        for shape in self.scene.shapes():
            if shape.id() == name and shape.emitter() is not None:
                return shape.emitter()
        for emitter in self.scene.emitters():
            if emitter.id() == name:
                return emitter
        raise RuntimeError(f"no emitter named {name!r} in the scene")  # a programming error, not user input

    def _object_bsdf(self):
        mi = self._mi
        if self.domain == "target":
            # Glossy: a fixed-weight blend of a diffuse base (the ψ colour) and a rough metal coat.  A
            # constant blend weight keeps the lobe choice independent of ψ (unlike roughplastic, whose
            # lobe-sampling weight is derived from the diffuse reflectance).
            return mi.load_dict({"type": "blendbsdf", "weight": 0.25,
                                 "bsdf_0": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5] * 3}},
                                 "bsdf_1": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.15}})
        return mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}})

    def _merged_meshes(self, state: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """The environment's meshes at ``state``, merged per material: {material: (V (N, 3), F (M, 3))}."""
        import torch

        meshes = self.env.meshes(torch.as_tensor(np.asarray(state, np.float64)))
        out: dict[str, tuple[list, list, int]] = {}
        for m in meshes:
            verts, faces, offset = out.setdefault(m.material, ([], [], 0))
            verts.append(m.vertices.detach().numpy())
            faces.append(m.faces.numpy() + offset)
            out[m.material] = (verts, faces, offset + m.vertices.shape[-2])
        return {k: (np.concatenate(v), np.concatenate(f)) for k, (v, f, _) in out.items()}

    def _make_bindings(self) -> list[_Binding]:
        """The ψ-dependent scene parameters, each linear in ψ (order of psi_specs: light, ambient,
        object rgb, floor rgb)."""
        target = self.domain == "target"

        def light(psi, aux):
            d2 = float(aux["light_distance"]) ** 2
            if target:  # area light: radiance L gives irradiance ≈ L · A / d² at the target
                area = float(aux["light_size"]) ** 2
                return psi[0] * LIGHT_IRRADIANCE * d2 / area * np.asarray(aux["light_color"])
            return psi[0] * LIGHT_IRRADIANCE * d2 * np.ones(3)

        def floor(i):
            def value(psi, aux):
                return psi[5:8] * np.asarray(floor_texture(str(aux["floor_texture"]), int(aux["texture_seed"]))[1 + i])
            return value

        obj_key = "mesh_object.bsdf.bsdf_0.reflectance.value" if target else "mesh_object.bsdf.reflectance.value"
        return [
            _Binding("light.emitter.radiance.value" if target else "light.intensity.value", light, "color", True),
            _Binding("ambient.scale", lambda psi, aux: np.asarray(psi[1]), "float", True) if target
            else _Binding("ambient.radiance.value", lambda psi, aux: psi[1] * np.ones(3), "color", True),
            _Binding(obj_key, lambda psi, aux: psi[2:5], "color"),
            _Binding("floor.bsdf.bsdf_0.reflectance.value", floor(0), "color"),
            _Binding("floor.bsdf.bsdf_1.reflectance.value", floor(1), "color"),
        ]

    # -- per-sample updates ---------------------------------------------------------------------------

    def _var(self, value: float, dtype=np.float32):
        """A one-element Dr.Jit array backed by memory, not a literal: literal values are compiled into
        the kernels, so new ψ values would mean new kernels (and Dr.Jit merges equal literals).

        ``dr.make_opaque`` copies the value into memory Dr.Jit allocates.  Built from a numpy array
        instead, the variable may point at numpy's buffer, whose alignment varies from call to call;
        the kernel's load instruction records that alignment, so the same render then compiled a new
        kernel every few samples (issue 9: measured as 1–3 s compiles among 0.1 s renders)."""
        mi, dr = self._mi, self._dr
        v = mi.UInt32(int(value)) if dtype == np.uint32 else mi.Float(float(value))
        dr.make_opaque(v)
        return v

    def _to_mitsuba(self, value: np.ndarray, kind: str):
        """ψ-dependent scene parameter value as memory-backed Dr.Jit arrays (see :meth:`_var`)."""
        mi = self._mi
        if kind == "color":
            return mi.Color3f(*[self._var(float(v)) for v in np.asarray(value).ravel()])
        return self._var(float(value))

    def _check_inputs(self, state, config: RenderConfig) -> tuple[np.ndarray, np.ndarray]:
        state = np.asarray(state, np.float64)
        if state.shape != (self.env.state_dim,):
            raise RispError(f"state must have shape ({self.env.state_dim},) for {self.env.name}, got {state.shape}")
        if not np.all(np.isfinite(state)):
            raise RispError("state contains NaN or infinite values")
        if not isinstance(config, RenderConfig):
            raise RispError("config must be a risp_data.psi.RenderConfig")
        psi = np.asarray(config.psi, np.float64)
        if psi.shape != (len(self.psi_names),):
            raise RispError(f"psi must have shape ({len(self.psi_names)},) for {self.env.name}, got {psi.shape}")
        if not np.all(np.isfinite(psi)):
            raise RispError("psi contains NaN or infinite values")
        return state, psi

    def set_state(self, state: np.ndarray) -> None:
        """Move the meshes to ``state`` (vertex positions in place; topology is fixed)."""
        mi = self._mi
        for material, (verts, _) in self._merged_meshes(state).items():
            self.params[self._mesh_keys[material]] = mi.Float(verts.astype(np.float32).ravel())

    def set_config(self, psi: np.ndarray, aux: dict, track: bool) -> None:
        """Write ψ and aux into the scene; with ``track``, enable gradients on the ψ-dependent parameters."""
        dr = self._dr
        try:
            self._set_aux(aux)
            self._leaves = []
            for b in self._bindings:
                value = self._to_mitsuba(b.value(psi, aux), b.kind)
                if track:
                    dr.enable_grad(value)
                self.params[b.key] = value
                self._leaves.append(value)
        except (KeyError, TypeError, ValueError, IndexError) as e:
            raise RispError(f"render config aux is missing or has a bad entry: {e!r}") from None

    def _set_aux(self, aux: dict) -> None:
        """Non-differentiable randomisation: light placement, floor pattern, (target) sky and gloss."""
        mi = self._mi
        cam_target = np.asarray(self.env.camera.target, np.float64)
        direction = np.asarray(aux["light_direction"], np.float64).reshape(3)
        distance = float(aux["light_distance"])
        if not (np.all(np.isfinite(direction)) and np.linalg.norm(direction) > 0 and math.isfinite(distance)
                and distance > 0):
            raise ValueError("light_direction must be a finite non-zero 3-vector and light_distance > 0")
        direction = direction / np.linalg.norm(direction)
        position = cam_target + distance * direction
        texture_key = (str(aux["floor_texture"]), int(aux["texture_seed"]))
        if texture_key != self._texture_key:  # re-upload the pattern only when it changes
            weight = floor_texture(*texture_key)[0]
            self.params["floor.bsdf.weight.data"] = mi.TensorXf(weight[..., None])
            self._texture_key = texture_key
        if self.domain == "target":
            size = float(aux["light_size"])
            M = _look_at(position, cam_target, _any_up(direction)) @ np.diag([size / 2, size / 2, 1.0, 1.0])
            self.params["light.to_world"] = mi.Transform4f(
                mi.Matrix4f([[self._var(M[i, j]) for j in range(4)] for i in range(4)]))
            sky_key = (tuple(map(float, aux["sky_zenith"])), tuple(map(float, aux["sky_horizon"])))
            if sky_key != self._sky_key:
                self.params["ambient.data"] = mi.TensorXf(sky_map(*sky_key))
                self._sky_key = sky_key
            self.params["mesh_object.bsdf.bsdf_1.alpha.value"] = self._var(float(aux["object_roughness"]))
            self.params["mesh_object.bsdf.weight.value"] = self._var(float(aux["object_gloss"]))
        else:
            self.params["light.position"] = mi.Point3f(*[self._var(float(p)) for p in position])

    # -- rendering -------------------------------------------------------------------------------------

    def render(self, state: np.ndarray, config: RenderConfig, seed: int, jacobian: bool = True,
               jacobian_path: str | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Image (H, W, 3) float32 linear RGB and, with ``jacobian``, J (K, H, W, 3) float32 with
        J[j] = ∂I/∂ψ_j, rendered with the random stream ``seed`` (same seed → same paths).

        ``jacobian_path`` overrides the renderer's (``fast`` or ``legacy``, JACOBIAN_PATHS) for this call;
        both give the same image and J up to float32 rounding (docs/rendering.md)."""
        path = self.jacobian_path if jacobian_path is None else jacobian_path
        if path not in JACOBIAN_PATHS:
            raise RispError(f"unknown Jacobian path {path!r}; choose one of: {', '.join(JACOBIAN_PATHS)}")
        state, psi = self._check_inputs(state, config)
        if not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) < 2**32:
            raise RispError(f"seed must be an integer in [0, 2^32), got {seed!r}")
        self.set_state(state)
        self.set_config(psi, config.aux, track=jacobian)
        self.params.update()
        seed_var = self._var(int(seed), np.uint32)
        H = W = self.resolution
        if jacobian and path == "fast":
            image, J = self._passes_fast(psi, config.aux, seed_var)
            return np.array(image, dtype=np.float32).reshape(H, W, 3), J
        tangents = self._tangents(psi, config.aux) if jacobian else []
        image, grads = self._passes(self.scene, seed_var, self._leaves, tangents)
        img = np.array(image, dtype=np.float32).reshape(H, W, 3)
        if not jacobian:
            return img, None
        J = np.stack([np.array(g, dtype=np.float32).reshape(H, W, 3) for g in grads])
        return img, J

    @property
    def mesh_keys(self) -> dict[str, str]:
        """{material: scene parameter key of its vertex positions} (risp_data.diff_render writes them)."""
        return dict(self._mesh_keys)

    @property
    def image_integrator(self) -> str:
        """Name of the integrator :meth:`render_reference` uses."""
        return self.settings.reference or self.settings.integrator

    def render_reference(self, state: np.ndarray, config: RenderConfig, seed: int) -> np.ndarray:
        """Image only (H, W, 3) float32, by the domain's reference integrator (target: Mitsuba's ``path``
        with Russian roulette, max depth 6; train: the same ``prb`` pass as :meth:`render`).

        Same expected image as ``render(..., jacobian=False)`` but independent noise: use :meth:`render`
        wherever images are compared with Jacobians (finite-difference checks, ``risp-data verify``).
        """
        if self.reference_integrator is None:
            return self.render(state, config, seed, jacobian=False)[0]
        state, psi = self._check_inputs(state, config)
        if not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) < 2**32:
            raise RispError(f"seed must be an integer in [0, 2^32), got {seed!r}")
        self.set_state(state)
        self.set_config(psi, config.aux, track=False)
        self.params.update()
        image = self._mi.render(self.scene, integrator=self.reference_integrator, seed=int(seed),
                                spp=self.spp * self.settings.spp_factor)
        H = W = self.resolution
        return np.array(image, dtype=np.float32).reshape(H, W, 3)

    def _tangent_values(self, psi: np.ndarray, aux: dict) -> list[list[np.ndarray]]:
        """T[j][k] = ∂p_k/∂ψ_j = P_k(e_j; aux) for every binding k (P_k is linear in ψ), as numpy."""
        out = []
        for j in range(len(psi)):
            e = np.zeros_like(psi)
            e[j] = 1.0
            out.append([np.asarray(b.value(e, aux), np.float64) for b in self._bindings])
        return out

    def _tangents(self, psi: np.ndarray, aux: dict) -> list[list]:
        """tangents[j][k] = P_k(e_j; aux) as Dr.Jit values (one forward pass per ψ_j: the legacy path)."""
        return [[self._to_mitsuba(t, b.kind) for t, b in zip(T, self._bindings)]
                for T in self._tangent_values(psi, aux)]

    def jacobian_plan(self, psi: np.ndarray, aux: dict) -> "JacobianPlan":
        """How the fast path gets each J_j (docs/rendering.md, "The fast Jacobian path")."""
        return self._plan(self._tangent_values(psi, aux))

    def _plan(self, T: list[list[np.ndarray]]) -> "JacobianPlan":
        emitters = [k for k, b in enumerate(self._bindings) if b.emitter]
        bound = {id(self._emitters[k]) for k in emitters} == {id(e) for e in self.scene.emitters()}
        return plan_jacobian(self.psi_names, T, [b.kind for b in self._bindings], emitters, all_emitters_bound=bound)

    def _passes_fast(self, psi: np.ndarray, aux: dict, seed) -> tuple:
        """Image and J (K, H, W, 3) float32 by the fast path: emitter-split primal passes and merged colour
        tangents (docs/rendering.md).  Same J as :meth:`_passes` up to float32 rounding."""
        mi, dr = self._mi, self._dr
        T = self._tangent_values(psi, aux)
        plan = self._plan(T)
        integ, scene = self.integrator, self.scene
        sensor = scene.sensors()[0]
        spp = self.spp * self.settings.spp_factor
        kw = dict(scene=scene, depth=mi.UInt32(0), active=mi.Bool(True))
        emitter_keys = [k for k, b in enumerate(self._bindings) if b.emitter]
        with dr.suspend_grad():
            sampler, spp = integ.prepare(sensor, seed, spp, integ.aov_names())
            ray, weight, pos = integ.sample_rays(scene, sensor, sampler)
            # (1) primal.  Emitter split: every emitter set to its tangent value ∂p_e/∂ψ_j(e), one pass that
            #     keeps each emitter's radiance L_e apart; then ∂L/∂ψ_j = Σ_{e driven by ψ_j} L_e and
            #     L = Σ_e ψ_j(e) L_e exactly (L is linear in the emitters).  Otherwise one ordinary primal.
            split = {}
            if plan.emitter:
                driver = {k: next(j for j in plan.emitter if np.any(T[j][k] != 0)) for k in emitter_keys}
                for k in emitter_keys:
                    self.params[self._bindings[k].key] = self._to_mitsuba(T[driver[k]][k], self._bindings[k].kind)
                self.params.update()
                per_emitter = sample_per_emitter(scene, sampler.clone(), ray, [self._emitters[k] for k in emitter_keys],
                                                 self.settings.max_depth, self.settings.rr_depth)
                for k in emitter_keys:  # back to the gradient-enabled values of ψ
                    self.params[self._bindings[k].key] = self._leaves[k]
                self.params.update()
                L_e = dict(zip(emitter_keys, per_emitter))
                split = {j: sum(L_e[k] for k in emitter_keys if driver[k] == j) for j in plan.emitter}
                L = sum(self._var(float(psi[driver[k]])) * L_e[k] for k in emitter_keys)
            else:
                L, _, _, _ = integ.sample(mode=dr.ADMode.Primal, sampler=sampler.clone(), ray=ray, δL=None,
                                          state_in=None, **kw)
            image = self._splat(pos, L * weight, spp)
            outputs = {("emitter", j): self._splat(pos, split[j] * weight, spp) for j in plan.emitter}
            # (2) forward-mode passes: one per merged colour group (tangent Σ_c T[j_c]) and per other ψ_j
            for name, group in [("group", g) for g in plan.groups] + [("single", (j,)) for j in plan.single]:
                with dr.resume_grad():
                    for k, leaf in enumerate(self._leaves):
                        t = sum(T[j][k] for j in group)
                        dr.set_grad(leaf, self._to_mitsuba(t, self._bindings[k].kind))
                # prb's forward mode without its geometric-derivative terms (ψ moves no geometry): same δL,
                # less to trace and run (risp_data/prb_passes.py)
                δL = forward_materials(scene, sampler.clone(), ray, L, self.settings.max_depth, self.settings.rr_depth)
                outputs[(name, group)] = self._splat(pos, δL * weight, spp)
            dr.eval(image, list(outputs.values()))
        H = W = self.resolution
        J = np.zeros((len(psi), H, W, 3), np.float32)
        for (name, which), value in outputs.items():
            arr = np.array(value, dtype=np.float32).reshape(H, W, 3)
            if name == "group":  # channel c of the merged pass is ∂I_c/∂ψ_{j_c}; other channels are exact 0
                for c, j in enumerate(which):
                    J[j, ..., c] = arr[..., c]
            else:
                J[which if name == "emitter" else which[0]] = arr
        return image, J

    def _passes(self, scene, seed, leaves, tangents):
        """One primal pass and one forward-mode pass per tangent, all sharing rays and sampler state.

        ``leaves``: the gradient-enabled ψ-dependent scene parameters (already in ``scene``);
        ``tangents[j][k]``: the tangent of leaves[k] along ψ_j.  Returns (image, [J_1 … J_K]) tensors.
        Pure in its inputs (no params.update() in here).  Not wrapped in ``dr.freeze``: with Mitsuba 3.9.1 /
        Dr.Jit 1.5 its replays re-recorded on every new ψ and, worse, some replays returned images computed
        with stale scene values (docs/rendering.md).
        """
        mi, dr = self._mi, self._dr
        integ = self.integrator
        sensor = scene.sensors()[0]
        spp = self.spp * self.settings.spp_factor
        grads = []
        with dr.suspend_grad():
            # (1) rays and the sampler state after ray generation, shared by every pass
            sampler, spp = integ.prepare(sensor, seed, spp, integ.aov_names())
            ray, weight, pos = integ.sample_rays(scene, sensor, sampler)
            # (2) primal pass: L and the replay state for the forward passes
            L, valid, aovs, state_out = integ.sample(
                mode=dr.ADMode.Primal, scene=scene, sampler=sampler.clone(), ray=ray, depth=mi.UInt32(0),
                δL=None, state_in=None, active=mi.Bool(True))
            image = self._splat(pos, L * weight, spp)
            # (3) one tangent pass per ψ_j: same sampler state → same paths as the primal
            for tangent in tangents:
                with dr.resume_grad():
                    for leaf, t in zip(leaves, tangent):
                        dr.set_grad(leaf, t)
                δL, _, _, _ = integ.sample(
                    mode=dr.ADMode.Forward, scene=scene, sampler=sampler.clone(), ray=ray,
                    depth=mi.UInt32(0), δL=None, δaovs=None, state_in=state_out, active=mi.Bool(True))
                grads.append(self._splat(pos, δL * weight, spp))
            dr.eval(image, grads)  # one launch for the primal and all tangent passes
        return image, grads

    def _splat(self, pos, value, spp: int):
        """Per-pixel mean of the samples' values: (H, W, 3) tensor.

        With the box reconstruction filter every sample lands in exactly the pixel containing its film
        position, so developing the film reduces to a scatter-add and a division by spp; unlike the
        film, separate buffers let all passes be evaluated together.
        """
        mi, dr = self._mi, self._dr
        H = W = self.resolution
        px = mi.Point2u(dr.clip(mi.Point2i(dr.floor(pos)), 0, W - 1))
        index = px.y * W + px.x
        out = dr.zeros(mi.Float, H * W * 3)
        for c in range(3):
            dr.scatter_reduce(dr.ReduceOp.Add, out, value[c] / spp, index * 3 + c)
        return mi.TensorXf(out, shape=(H, W, 3))


JACOBIAN_PATHS: tuple[str, ...] = ("fast", "legacy")


@dataclass(frozen=True)
class JacobianPlan:
    """Which pass gives each J_j on the fast path.

    ``emitter``: ψ_j that only scale emitters (J_j is a primal pass with the emitters set to P(e_j));
    ``groups``: (j_R, j_G, j_B) triples whose tangents each live in one colour channel (one merged
    forward pass, split by channel); ``single``: every other ψ_j (one forward pass each)."""

    emitter: tuple[int, ...]
    groups: tuple[tuple[int, int, int], ...]
    single: tuple[int, ...]


def plan_jacobian(names, T, kinds, emitters, all_emitters_bound: bool) -> JacobianPlan:
    """Classify every ψ_j from its tangents T[j][k] = ∂p_k/∂ψ_j (docs/rendering.md says why each is exact).

    Emitter split: every binding ψ_j moves is an emitter, no other ψ moves an emitter, every emitter
    binding is moved by exactly one ψ (one pass then separates them by emitter), and every emitter of the
    scene is a binding (else I ≠ Σ_j ψ_j ∂I/∂ψ_j).  Colour group: ψ named ``<x>_r``, ``<x>_g``,
    ``<x>_b`` whose tangents are non-zero only in their own channel of colour bindings (the ``rgb``
    variant never mixes channels, so one pass with the summed tangent carries all three)."""
    K = len(names)
    moves = [{k for k, t in enumerate(T[j]) if np.any(t != 0)} for j in range(K)]
    emitter_j = [j for j in range(K) if moves[j] and moves[j] <= set(emitters)]
    others_touch = any(moves[j] & set(emitters) for j in range(K) if j not in emitter_j)
    one_driver = all(sum(k in moves[j] for j in emitter_j) == 1 for k in emitters)
    if not all_emitters_bound or others_touch or not one_driver:
        emitter_j = []
    groups, used = [], set(emitter_j)
    for j, name in enumerate(names):
        if not name.endswith("_r") or j in used:
            continue
        trio = [names.index(name[:-1] + c) if name[:-1] + c in names else None for c in "rgb"]
        if None in trio or used & set(trio):
            continue
        own = all(kinds[k] == "color" and all(T[jc][k][c2] == 0 for c2 in range(3) if c2 != c)
                  for c, jc in enumerate(trio) for k in moves[jc])
        if own:
            groups.append(tuple(trio))
            used |= set(trio)
    single = tuple(j for j in range(K) if j not in used)
    return JacobianPlan(tuple(emitter_j), tuple(groups), single)


def _look_at(origin: np.ndarray, target: np.ndarray, up) -> np.ndarray:
    """Mitsuba's look_at as a 4×4 numpy matrix: columns (left, up', forward, origin)."""
    fwd = (target - origin) / np.linalg.norm(target - origin)
    left = np.cross(up, fwd)
    left /= np.linalg.norm(left)
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = left, np.cross(fwd, left), fwd, origin
    return M


def _any_up(direction: np.ndarray) -> list[float]:
    """An up vector not parallel to ``direction`` (for look_at)."""
    return [0.0, 1.0, 0.0] if abs(direction[2]) > 0.99 else [0.0, 0.0, 1.0]


__all__ = ["Renderer", "DOMAIN_SETTINGS", "JACOBIAN_PATHS", "JacobianPlan", "plan_jacobian", "floor_texture", "sky_map"]
