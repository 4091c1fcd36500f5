"""Two lean passes of Mitsuba's path-replay integrator ``prb`` for the fast Jacobian path (issue 9).

Both follow ``mitsuba/python/ad/integrators/prb.py`` (Mitsuba 3.9, BSD-3-Clause, © Wenzel Jakob and
contributors) line for line — the same intersections and the same random numbers in the same order
(emitter sample, BSDF sample, Russian-roulette draw), so they trace the same paths as ``prb`` and as each
other when given clones of one sampler state — with one change each:

- :func:`sample_per_emitter` (primal): each emitted term, ``Le`` (an emitter hit) and ``Lr_dir``
  (next-event estimation), is added to the accumulator of the emitter it came from instead of to one L.
  Σ_e L_e is ``prb``'s primal L up to the order of float additions.
- :func:`forward_materials` (forward mode, from the primal's per-ray L): ``prb``'s terms that only carry
  *geometric* derivatives are left out — the re-attached incident direction at depth ≥ 1, the
  re-attached emitter sample with its solid-angle-to-area Jacobian, the re-attached outgoing direction
  with its Jacobian (one more surface interaction per vertex).  With no gradient-enabled geometry those
  terms have value 1 (``dr.relative_grad``) or their detached value (``dr.replace_grad``) and zero
  derivative, so δL is unchanged (bitwise equal in our comparisons) and there is less to trace and run.
  Not for derivatives w.r.t. vertex positions or transforms (docs/rendering.md).

Why each gives exact Jacobians: docs/rendering.md, "The fast Jacobian path".
"""

from __future__ import annotations

_LABELS = ("sampler", "ray", "depth", "acc", "β", "η", "active", "pi", "si_prev", "bsdf_pdf_prev", "bsdf_delta_prev")


def _trace(scene, sampler, ray, acc: tuple, body, max_depth: int, label: str) -> tuple:
    """Run ``body`` as ``prb``'s symbolic path loop from the camera rays; returns the final ``acc``.

    Loop state (as in prb): sampler, ray, depth, acc (the pass's accumulators), throughput β, η, active,
    preliminary intersection pi, and the previous vertex (si, BSDF pdf, delta flag) for MIS."""
    import drjit as dr
    import mitsuba as mi

    ray = mi.Ray3f(dr.detach(ray))
    active = mi.Bool(True)
    state = (sampler, ray, mi.UInt32(0), acc, mi.Spectrum(1), mi.Float(1), active,
             scene.ray_intersect_preliminary(ray, coherent=True, reorder=False, active=active),
             dr.zeros(mi.SurfaceInteraction3f), mi.Float(1.0), mi.Bool(True))
    state = dr.while_loop(state, lambda *s: s[6], body, max_iterations=max_depth, label=label, labels=_LABELS)
    return state[3]


def _continue_path(scene, sampler, si, bsdf_sample, bsdf_weight, β, η, depth, active_next, rr_depth: int):
    """prb's step to the next vertex: next ray, throughput, the stopping tests (zero throughput; the
    Russian-roulette draw is made even where roulette is off), and the next intersection."""
    import drjit as dr
    import mitsuba as mi

    ray_next = si.spawn_ray(si.to_world(bsdf_sample.wo))
    η = η * bsdf_sample.eta
    β = β * bsdf_weight
    β_max = dr.max(mi.unpolarized_spectrum(β))
    active_next &= β_max != 0
    rr_prob = dr.minimum(β_max * η**2, 0.95)
    rr_active = depth >= rr_depth
    β[rr_active] *= dr.rcp(rr_prob)
    rr_continue = sampler.next_1d() < rr_prob
    active_next &= ~rr_active | rr_continue
    pi_next = scene.ray_intersect_preliminary(ray_next, coherent=False, reorder=False, active=active_next)
    si_prev = dr.detach(si, True)
    delta = mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Delta)
    return ray_next, β, η, active_next, pi_next, si_prev, bsdf_sample.pdf, delta


def _next_depth(si, pi_next, active_next, depth):
    """prb's thread-reordering hint (a no-op on the CPU) and the depth increment on valid hits."""
    import drjit as dr
    import mitsuba as mi

    reorder_hint = dr.reinterpret_array(mi.UInt32, pi_next.shape)
    reorder_hint = (reorder_hint << 1) | dr.select(active_next, 1, 0)
    depth = dr.reorder_threads(reorder_hint, 16, depth)
    depth[si.is_valid()] += 1
    return depth


def sample_per_emitter(scene, sampler, ray, emitters: list, max_depth: int, rr_depth: int) -> list:
    """Per-emitter primal radiance of ``prb`` (``hide_emitters`` false): one ``mi.Spectrum`` per emitter."""
    import drjit as dr
    import mitsuba as mi
    from mitsuba.ad.integrators.common import mis_weight

    ptrs = [mi.EmitterPtr(e) for e in emitters]
    ctx = mi.BSDFContext()

    def body(sampler, ray, depth, Ls, β, η, active, pi, si_prev, bsdf_pdf_prev, bsdf_delta_prev):
        active_next = mi.Bool(active)
        si = pi.compute_surface_interaction(ray, ray_flags=mi.RayFlags.All)
        bsdf = si.bsdf(ray)
        # -- direct emission (an emitter hit by the previous bounce's BSDF sample), MIS-weighted
        ds = mi.DirectionSample3f(scene, si=si, ref=si_prev)
        mis = mis_weight(bsdf_pdf_prev, scene.pdf_emitter_direction(si_prev, ds, ~bsdf_delta_prev))
        Le = β * mis * ds.emitter.eval(si, active_next)
        # -- emitter sampling
        active_next &= (depth + 1 < max_depth) & si.is_valid()
        active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        ds_em, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
        active_em &= ds_em.pdf != 0.0
        bsdf_value_em, bsdf_pdf_em = bsdf.eval_pdf(ctx, si, si.to_local(ds_em.d), active_em)
        mis_em = dr.select(ds_em.delta, 1, mis_weight(ds_em.pdf, bsdf_pdf_em))
        Lr_dir = β * mis_em * bsdf_value_em * em_weight
        # -- BSDF sampling
        bsdf_sample, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)
        # -- the one change to prb: each emitted term goes to its emitter's accumulator
        Ls = tuple(L + dr.select(ds.emitter == e, Le, 0) + dr.select(ds_em.emitter == e, Lr_dir, 0)
                   for L, e in zip(Ls, ptrs))
        ray_next, β, η, active_next, pi_next, si_prev, bsdf_pdf_prev, bsdf_delta_prev = _continue_path(
            scene, sampler, si, bsdf_sample, bsdf_weight, β, η, depth, active_next, rr_depth)
        depth = _next_depth(si, pi_next, active_next, depth)
        return sampler, ray_next, depth, Ls, β, η, active_next, pi_next, si_prev, bsdf_pdf_prev, bsdf_delta_prev

    acc = tuple(mi.Spectrum(0) for _ in ptrs)
    return list(_trace(scene, sampler, ray, acc, body, max_depth, "risp emitter-split primal"))


def forward_materials(scene, sampler, ray, L, max_depth: int, rr_depth: int):
    """δL per ray: ``prb``'s forward mode (state_in = the primal's per-ray ``L``) along the tangents set
    with ``dr.set_grad`` on BSDF / emitter values; geometric-derivative terms left out (module doc)."""
    import drjit as dr
    import mitsuba as mi
    from mitsuba.ad.integrators.common import mis_weight

    ctx = mi.BSDFContext()

    def body(sampler, ray, depth, acc, β, η, active, pi, si_prev, bsdf_pdf_prev, bsdf_delta_prev):
        L, δL = acc  # L: the radiance still to come along the path (the primal's estimate at the start)
        active_next = mi.Bool(active)
        si = pi.compute_surface_interaction(ray, ray_flags=mi.RayFlags.All)
        bsdf = si.bsdf(ray)
        # -- direct emission, differentiable in the emitter's value
        ds = mi.DirectionSample3f(scene, si=si, ref=si_prev)
        mis = mis_weight(bsdf_pdf_prev, scene.pdf_emitter_direction(si_prev, ds, ~bsdf_delta_prev))
        with dr.resume_grad():
            Le = β * mis * ds.emitter.eval(si, active_next)
        # -- emitter sampling (detached), its contribution re-evaluated differentiably
        active_next &= (depth + 1 < max_depth) & si.is_valid()
        active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
        active_em &= ds.pdf != 0.0
        with dr.resume_grad():
            em_val_diff = scene.eval_emitter_direction(si, ds, active_em)
            inv_ds_pdf = dr.select(ds.pdf != 0, dr.rcp(ds.pdf), 0)
            em_weight = dr.replace_grad(em_weight, em_val_diff * dr.detach(inv_ds_pdf))
            bsdf_value_em, bsdf_pdf_em = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), active_em)
            mis_em = dr.select(ds.delta, 1, mis_weight(ds.pdf, bsdf_pdf_em))
            Lr_dir = β * mis_em * bsdf_value_em * em_weight
        # -- detached BSDF sampling; L becomes the radiance still to come after this vertex
        bsdf_sample, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)
        L = L - Le - Lr_dir
        ray_next, β, η, active_next, pi_next, si_prev, bsdf_pdf_prev, bsdf_delta_prev = _continue_path(
            scene, sampler, si, bsdf_sample, bsdf_weight, β, η, depth, active_next, rr_depth)
        # -- the reflected radiance to come, differentiable in this vertex's BSDF value
        with dr.resume_grad():
            bsdf_val = bsdf.eval(ctx, si, si.to_local(ray_next.d), active_next)
            δL += dr.forward_to(Le + Lr_dir + L * dr.relative_grad(bsdf_val))
        depth = _next_depth(si, pi_next, active_next, depth)
        return sampler, ray_next, depth, (L, δL), β, η, active_next, pi_next, si_prev, bsdf_pdf_prev, bsdf_delta_prev

    return _trace(scene, sampler, ray, (mi.Spectrum(L), mi.Spectrum(0)), body, max_depth, "risp material forward")[1]
