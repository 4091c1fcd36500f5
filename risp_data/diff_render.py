"""Differentiable rendering of simulated states: a torch function ``states (T, S) -> images (T, H, W, 3)``
with gradients w.r.t. the states through the geometry, silhouettes included (issue 10, item 1).

Chain (all derivatives analytic, no finite differences):

    states (T, S) --env.meshes (torch)--> vertex positions V_t (per material)
                  --dr.wrap(torch -> drjit)--> I_t = render(scene(V_t); ψ)  (Mitsuba, projective integrator)

∂I/∂V comes from a projective integrator (``prb_projective``; ``direct_projective`` on request) in its
``_flat`` variant (:mod:`risp_data.flat_projective`): Mitsuba's path-replay derivatives in the interior of
shapes plus a primary-visibility boundary term that is right for our flat-shaded meshes (crease edges,
silhouettes on their front face, point-light shadow edges, curves where parts interpenetrate), which
Mitsuba's own term is not.  Guiding is switched off (``'guiding': 'none'``): with the default guiding one
backward pass took 6–9 s at 64×64 on a 2-core machine, without it ≈0.1 s.

The scene is the one :class:`risp_data.render.Renderer` builds (same meshes, materials, lights, camera,
ψ bindings), and the primal image is rendered by its own integrator, so images have the shards'
expectation.  The gradient's interior term uses paths of at most ``grad_max_depth`` = 2 segments (direct
light): with the data's indirect bounce it was heavy-tailed near concave contacts (the die pips the cube had then).
The boundary radiances f_in, f_out use the primal's paths, except for the environments of ``BOUNDARY_PATHS``
(the cube, the quadrotor), whose lit concave corners make the bounce's near-field peak a jump the 2-segment
interior cannot cancel (the cube's whole-image derivative 138 against FD 70 with 3 segments, 78 with 2).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .errors import RispError
from .psi import RenderConfig, nominal_rendering
from .render import Renderer

INTEGRATORS: tuple[str, ...] = ("prb_projective", "direct_projective")
# Path length (segments) of the boundary radiances f_in, f_out where it is not the primal's (the data's 3, one
# bounce): the interior's 2 for the environments whose parts meet in lit concave corners (the cube's stickers,
# the quadrotor's rotors and arms).  There the bounce brightens a face at a corner's foot over a fraction of a
# millimetre, and a jump that counted it would count that near-field peak without the decay that cancels it, an
# interior derivative of the bounce the 2-segment gradient paths drop; elsewhere the bounce is a real part of a
# silhouette's jump (the hand and the rod against the floor).  Measured, not derived: ‖g − fd‖ / ‖fd‖ of the whole
# state gradient (benchmarks/diff_render_fd.py, 8 seeds) with 2 / 3 segments — cube 0.35 / 1.58, quadrotor
# 0.03 / 0.84, hand 0.31 / 0.20, rod 1.02 / 0.40 at state seed 1; rod 0.56 / 0.19 at seed 2 (docs/tasks.md
# §Shadows, bounces, stickers).
BOUNDARY_PATHS: dict[str, int] = {"cube": 2, "quadrotor": 2}
BOUNDARIES: tuple[str, ...] = ("flat", "mitsuba")  # whose primary-visibility boundary term (docs/tasks.md)


def _positive_int(value) -> bool:
    """Whether ``value`` is a whole number >= 1 (3 and 3.0, not 2.5, "3", None, NaN or inf): for a one-line RispError
    instead of the ValueError or TypeError that int() raises on a string."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and \
        value >= 1 and int(value) == value


class StateRenderer:
    """Render states of one environment in one look; differentiable w.r.t. the states.

    ``config``: the look ψ (and its aux); None gives the domain's nominal look
    (:func:`risp_data.psi.nominal_rendering`).  ``spp``: samples per pixel of the gradient pass;
    ``primal_spp`` (None: ``spp``) those of the images returned, which a render loss's network reads
    (docs/tasks.md §Primal spp).  :meth:`set_look` may change the look between calls: each frame's backward pass
    runs in the look its forward pass was rendered in.  ``boundary_max_depth``: path length of the flat boundary term's radiances
    (None: ``BOUNDARY_PATHS``, else the primal's).  Frame t of a call is rendered with the random stream
    ``frame_seed(seed, t)``, so the same (states, seed) give the same images; the gradient pass uses an
    independent stream (Mitsuba's ``seed_grad``), which keeps the gradient estimate unbiased.
    """

    def __init__(self, env: str, resolution: int = 64, spp: int = 8, domain: str = "train",
                 config: RenderConfig | None = None, integrator: str = "prb_projective", variant: str | None = None,
                 grad_max_depth: int = 2, boundary: str = "flat", primal_spp: int | None = None,
                 boundary_max_depth: int | None = None):
        if integrator not in INTEGRATORS:
            raise RispError(f"unknown differentiable integrator {integrator!r}; choose one of: {', '.join(INTEGRATORS)}")
        if boundary not in BOUNDARIES:
            raise RispError(f"unknown gradient boundary term {boundary!r}; choose one of: {', '.join(BOUNDARIES)}")
        self.boundary = boundary
        if boundary_max_depth is not None and not _positive_int(boundary_max_depth):
            raise RispError(f"boundary_max_depth must be a positive integer, got {boundary_max_depth!r}")
        self.renderer = Renderer(env, domain=domain, resolution=resolution, spp=spp, variant=variant)
        self.env = self.renderer.env
        self.resolution = self.renderer.resolution
        if primal_spp is not None and not _positive_int(primal_spp):
            raise RispError(f"primal_spp must be a positive integer, got {primal_spp!r}")
        self.spp = self.renderer.spp * self.renderer.settings.spp_factor
        self.primal_spp = (int(primal_spp) if primal_spp is not None else spp) * self.renderer.settings.spp_factor
        import drjit as dr
        import mitsuba as mi

        self._mi, self._dr = mi, dr
        from .flat_projective import register

        register()
        # primal: the data renderer's own integrator (same image expectation as the shards); gradients: the
        # "_flat" variant of the projective integrator (risp_data/flat_projective.py: boundary terms right for
        # flat-shaded meshes, point-light shadows), with paths of at most ``grad_max_depth`` segments
        self.primal_integrator = self.renderer.integrator
        settings = self.renderer.settings
        self.boundary_max_depth = (int(boundary_max_depth) if boundary_max_depth is not None
                                   else BOUNDARY_PATHS.get(self.env.name, settings.max_depth))
        # (boundary="mitsuba": Mitsuba's own integrator, biased for flat-shaded meshes but cheaper and less
        # noisy at a few spp; kept selectable so the two can be compared on a task)
        flat = boundary == "flat"
        props = {"type": integrator + ("_flat" if flat else ""), "max_depth": min(settings.max_depth, grad_max_depth),
                 "guiding": "none"}
        if integrator == "prb_projective":
            props["rr_depth"] = settings.rr_depth
            if flat:
                props["boundary_max_depth"] = self.boundary_max_depth
        self.integrator = mi.load_dict(props)
        self.set_look(config if config is not None else nominal_rendering(env, domain))
        self._render_frame = self._make_frame_renderer()

    def set_look(self, config: RenderConfig) -> None:
        """Write the look ψ (and aux) into the scene; later renders use it."""
        psi = np.asarray(config.psi, np.float64) if isinstance(config, RenderConfig) else None
        if psi is None or psi.shape != (len(self.renderer.psi_names),) or not np.all(np.isfinite(psi)):
            raise RispError(f"the look must be a RenderConfig with {len(self.renderer.psi_names)} finite ψ values")
        self.renderer.set_config(psi, config.aux, track=False)
        self.renderer.params.update()
        self.config = config

    def _make_frame_renderer(self):
        """A torch autograd function rendering one frame.

        Forward renders the primal; backward writes the frame's vertices into the scene again and runs the
        integrator's ``render_backward``.  ``dr.wrap`` around ``mi.render`` alone would be wrong for a
        sequence: its backward runs after all frames were rendered and would differentiate the scene as the
        *last* frame left it.
        """
        mi, dr = self._mi, self._dr
        params, scene, integrator, spp = self.renderer.params, self.renderer.scene, self.integrator, self.spp
        primal_spp = self.primal_spp
        primal_integrator = self.primal_integrator
        keys = self.renderer.mesh_keys

        def write(vertices: dict, grad: bool) -> list:
            leaves = []
            for material, v in vertices.items():
                flat = mi.Float(v.array)  # (V, 3) tensor -> flat Float, as Mitsuba stores positions
                if grad:
                    dr.enable_grad(flat)
                params[keys[material]] = flat
                leaves.append(flat)
            params.update()
            return leaves

        @dr.wrap(source="torch", target="drjit")
        def primal(vertices: dict, seed: int):
            with dr.suspend_grad():
                write(vertices, grad=False)
                return mi.render(scene, params, integrator=primal_integrator, seed=seed, spp=primal_spp)

        @dr.wrap(source="torch", target="drjit")
        def vjp(vertices: dict, grad_image, seed: int):
            leaves = write(vertices, grad=True)
            integrator.render_backward(scene, params, grad_image, seed=seed + 1, spp=spp)
            return [dr.grad(leaf) for leaf in leaves]

        materials = list(keys)
        # dr.wrap maps a tensor to the Dr.Jit backend of its torch device (CPU tensors to LLVM arrays): with
        # cuda_ad_rgb the vertices must travel to the GPU, and the image and gradients come back to the caller's
        # device
        backend = torch.device("cuda") if self.renderer.variant.startswith("cuda") else torch.device("cpu")

        renderer = self

        class RenderFrame(torch.autograd.Function):
            @staticmethod
            def forward(ctx, seed, *verts):
                ctx.seed = seed
                ctx.look = renderer.config  # the backward differentiates the look this frame was rendered in
                ctx.save_for_backward(*verts)
                with _quiet(mi):
                    image = primal(dict(zip(materials, [v.to(backend) for v in verts])), seed)
                return image.to(verts[0].device)

            @staticmethod
            def backward(ctx, grad_image):
                verts = ctx.saved_tensors
                if renderer.config is not ctx.look:  # a loss that reads several looks (set_look between frames)
                    renderer.set_look(ctx.look)
                with _quiet(mi):
                    grads = vjp(dict(zip(materials, [v.to(backend) for v in verts])),
                                grad_image.to(backend).contiguous(), ctx.seed)
                return (None, *[g.reshape(v.shape).to(v.device) for g, v in zip(grads, verts)])

        def render_frame(vertices: dict, seed: int) -> torch.Tensor:
            return RenderFrame.apply(seed, *[vertices[m] for m in materials])

        return render_frame

    def vertices(self, state: torch.Tensor) -> dict[str, torch.Tensor]:
        """{material: (V, 3) float32} world-space vertices of one state, merged per material in the order of
        :meth:`Renderer._merged_meshes` (the scene's vertex buffers); differentiable w.r.t. ``state``."""
        out: dict[str, list[torch.Tensor]] = {}
        for m in self.env.meshes(state):
            out.setdefault(m.material, []).append(m.vertices)
        return {k: torch.cat(v, 0).to(torch.float32).contiguous() for k, v in out.items()}

    def in_view(self, states: torch.Tensor) -> np.ndarray:
        """Fraction of the object's vertices inside the camera's image, per state: (T,) in [0, 1], occlusion
        ignored.  A state at 0 has left the view: its render shows no part of the object, so an image loss
        compares the empty scene and has no gradient that could bring the object back (docs/tasks.md §Out of
        view).  A vertex is inside when Mitsuba's sensor samples a direction to it with non-zero density."""
        mi, dr = self._mi, self._dr
        with torch.no_grad():
            per_state = [torch.cat(list(self.vertices(state).values()), 0).cpu().numpy() for state in states]
        if not per_state:
            return np.zeros(0)
        V = np.concatenate(per_state, 0)  # every state's vertices in one sensor query
        with dr.suspend_grad():
            it = dr.zeros(mi.Interaction3f, len(V))
            it.p = mi.Point3f(*[mi.Float(np.ascontiguousarray(V[:, c])) for c in range(3)])
            ds, _ = self.renderer.scene.sensors()[0].sample_direction(it, mi.Point2f(0))
            inside = ds.pdf.numpy() > 0
        ends = np.cumsum([len(v) for v in per_state])
        return np.asarray([part.mean() if len(part) else 0.0 for part in np.split(inside, ends[:-1])], np.float64)

    def __call__(self, states: torch.Tensor, *, seed: int) -> torch.Tensor:
        """Images (T, H, W, 3) float32 linear RGB of states (T, S); differentiable w.r.t. ``states``."""
        S = self.env.state_dim
        if not torch.is_tensor(states) or states.ndim != 2 or states.shape[1] != S:
            shape = tuple(states.shape) if torch.is_tensor(states) else type(states).__name__
            raise RispError(f"states must be a (T, {S}) tensor for {self.env.name}, got {shape}")
        if not torch.isfinite(states).all():
            raise RispError("states contain NaN or inf")
        frames = [self._render_frame(self.vertices(s), frame_seed(seed, t)) for t, s in enumerate(states)]
        return torch.stack(frames)


class _quiet:
    """Silence Mitsuba's warning that shapes may leave the viewport (``sample_border``) while rendering:
    the environments keep their objects in view, and the warning would repeat for every frame."""

    def __init__(self, mi):
        self.logger = mi.Thread.thread().logger()

    def __enter__(self):
        import mitsuba as mi

        self.level = self.logger.log_level()
        self.logger.set_log_level(mi.LogLevel.Error)

    def __exit__(self, *exc):
        self.logger.set_log_level(self.level)


def frame_seed(seed: int, t: int) -> int:
    """Random stream of frame t: distinct for every (seed, t), even numbers (seed_grad uses seed + 1)."""
    return int(np.random.SeedSequence([int(seed), int(t)]).generate_state(1)[0] & 0x7FFFFFFE)


__all__ = ["INTEGRATORS", "StateRenderer", "frame_seed", "set_camera"]


def set_camera(renderer: Renderer, camera) -> None:
    """Replace the scene camera of ``renderer`` (a :class:`risp_data.envs.Camera`: look-at and horizontal fov)."""
    import mitsuba as mi

    renderer.params["sensor.to_world"] = mi.Transform4f().look_at(origin=list(camera.origin), target=list(camera.target),
                                                                   up=list(camera.up))
    renderer.params["sensor.x_fov"] = float(camera.fov)
    renderer.params.update()
