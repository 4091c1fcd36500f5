"""One primal pass of Mitsuba's ``prb`` that keeps each emitter's contribution apart (issue 9).

``sample_per_emitter(scene, sampler, ray, emitters, max_depth, rr_depth)`` returns [L_e for e in
emitters]: the radiance estimate of every camera ray, split by the emitter that emitted it, so that
Σ_e L_e is exactly the ``L`` of ``prb.sample(mode=Primal)`` for the same sampler state (up to the order
of float additions).  It is the primal half of ``mitsuba/python/ad/integrators/prb.py`` (Mitsuba 3.9,
BSD-3-Clause, © Wenzel Jakob and contributors), line for line — the same intersections, the same
random numbers consumed in the same order (emitter sample, BSDF sample, Russian-roulette draw), so
the paths are the ones the forward-mode replays of ``prb`` follow — with one change: each emitted term
``Le`` (an emitter hit) and ``Lr_dir`` (next-event estimation) is added to the accumulator of the
emitter it came from (``ds.emitter``), instead of to one ``L``.

Used by :meth:`risp_data.render.Renderer._passes_fast`: with every emitter set to its tangent value
∂p_e/∂ψ_j, L_e is ∂L/∂ψ_j of the ψ_j that drives emitter e (docs/rendering.md, "The fast Jacobian path").
"""

from __future__ import annotations


def sample_per_emitter(scene, sampler, ray, emitters: list, max_depth: int, rr_depth: int) -> list:
    """Per-emitter primal radiance of ``prb`` (``hide_emitters`` false), one ``mi.Spectrum`` per emitter."""
    import drjit as dr
    import mitsuba as mi
    from mitsuba.ad.integrators.common import mis_weight

    ptrs = [mi.EmitterPtr(e) for e in emitters]

    bsdf_ctx = mi.BSDFContext()

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
        wo = si.to_local(ds_em.d)
        bsdf_value_em, bsdf_pdf_em = bsdf.eval_pdf(bsdf_ctx, si, wo, active_em)
        mis_em = dr.select(ds_em.delta, 1, mis_weight(ds_em.pdf, bsdf_pdf_em))
        Lr_dir = β * mis_em * bsdf_value_em * em_weight

        # -- BSDF sampling
        bsdf_sample, bsdf_weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)

        # -- the one change to prb: each emitted term goes to its emitter's accumulator
        Ls = tuple(L + dr.select(ds.emitter == e, Le, 0) + dr.select(ds_em.emitter == e, Lr_dir, 0)
                   for L, e in zip(Ls, ptrs))
        ray_next = si.spawn_ray(si.to_world(bsdf_sample.wo))
        η = η * bsdf_sample.eta
        β = β * bsdf_weight
        si_prev = dr.detach(si, True)
        bsdf_pdf_prev = bsdf_sample.pdf
        bsdf_delta_prev = mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Delta)

        # -- stopping: zero throughput, Russian roulette (the draw is made even when it is off, as in prb)
        β_max = dr.max(mi.unpolarized_spectrum(β))
        active_next &= β_max != 0
        rr_prob = dr.minimum(β_max * η**2, 0.95)
        rr_active = depth >= rr_depth
        β[rr_active] *= dr.rcp(rr_prob)
        rr_continue = sampler.next_1d() < rr_prob
        active_next &= ~rr_active | rr_continue

        pi_next = scene.ray_intersect_preliminary(ray_next, coherent=False, reorder=False, active=active_next)
        reorder_hint = dr.reinterpret_array(mi.UInt32, pi_next.shape)
        reorder_hint = (reorder_hint << 1) | dr.select(active_next, 1, 0)
        depth = dr.reorder_threads(reorder_hint, 16, depth)
        depth[si.is_valid()] += 1
        return sampler, ray_next, depth, Ls, β, η, active_next, pi_next, si_prev, bsdf_pdf_prev, bsdf_delta_prev

    ray = mi.Ray3f(dr.detach(ray))
    active = mi.Bool(True)
    state = (
        sampler,
        ray,
        mi.UInt32(0),  # depth
        tuple(mi.Spectrum(0) for _ in ptrs),  # one radiance accumulator per emitter
        mi.Spectrum(1),  # β: path throughput
        mi.Float(1),  # η
        active,
        scene.ray_intersect_preliminary(ray, coherent=True, reorder=False, active=active),
        dr.zeros(mi.SurfaceInteraction3f),  # si_prev
        mi.Float(1.0),  # bsdf_pdf_prev
        mi.Bool(True),  # bsdf_delta_prev
    )
    state = dr.while_loop(state, lambda *s: s[6], body, max_iterations=max_depth, label="risp emitter-split primal",
                          labels=("sampler", "ray", "depth", "Ls", "β", "η", "active", "pi", "si_prev",
                                  "bsdf_pdf_prev", "bsdf_delta_prev"))
    return list(state[3])
