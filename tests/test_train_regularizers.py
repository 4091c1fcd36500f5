"""The RISP regularizers in float64 on a tiny network: values and parameter gradients vs finite differences.

No shards needed: the math is checked on random inputs and tangents (the tangents play the role of the
stored ∂x/∂ψ_j).  Gradients are compared with central differences along random directions in parameter
space (covers every parameter at once) and at single coordinates of every parameter tensor.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from risp_train.model import ModelConfig, ResNet18, build_model
from risp_train.norms import InstanceNorm, instance_norm
from risp_train.normalization import Normalization, StatsAccumulator
from risp_train.regularizers import (
    SQRT_2_OVER_PI,
    exact_regularizer,
    gamma_at,
    rendering_gradients,
    risp_loss,
    state_error,
    stochastic_regularizer,
    surrogate_regularizer,
)

B, K, T, H = 2, 3, 3, 16


@pytest.fixture(scope="module")
def setup():
    net = build_model(ModelConfig(out_dim=T, width=2, blocks=(1, 1, 1, 1), stem="small"), seed=0).double()
    g = torch.Generator().manual_seed(1)
    x = torch.randn(B, 3, H, H, generator=g, dtype=torch.float64)
    tangents = torch.randn(B, K, 3, H, H, generator=g, dtype=torch.float64)
    y = torch.randn(B, T, generator=g, dtype=torch.float64)
    v = torch.randn(B, K, generator=g, dtype=torch.float64)
    return net, x, tangents, y, v


def _objective(kind, net, x, tangents, y, v):
    if kind == "exact":
        return exact_regularizer(net, x, tangents)[1].sum()
    if kind == "exact-functorch":
        return exact_regularizer(net, x, tangents, engine="functorch")[1].sum()
    if kind == "stochastic-functorch":
        return stochastic_regularizer(net, x, tangents, v, engine="functorch")[1].sum()
    if kind == "surrogate":
        return surrogate_regularizer(net, x, tangents, y)[2].sum()
    if kind == "stochastic":
        return stochastic_regularizer(net, x, tangents, v)[1].sum()
    if kind.startswith("loss-"):  # the calibrated training loss L = mean ℓ + γ R, ψ scaled by σ_ψ
        scale = torch.tensor([0.5, 2.0, 1.3], dtype=torch.float64)
        return risp_loss(net, x, y, kind[5:], 0.7, tangents, torch.Generator().manual_seed(3), scale).total
    raise AssertionError(kind)


def _grads(f, params):
    gs = torch.autograd.grad(f(), params, allow_unused=True)
    return [torch.zeros_like(p) if g is None else g for g, p in zip(gs, params)]


@pytest.mark.parametrize("kind", ["exact", "surrogate", "stochastic", "exact-functorch", "stochastic-functorch",
                                  "loss-exact", "loss-surrogate", "loss-stochastic"])
def test_parameter_gradient_matches_central_differences(setup, kind):
    net, x, tangents, y, v = setup
    params = list(net.parameters())
    f = lambda: _objective(kind, net, x, tangents, y, v)  # noqa: E731
    grads = _grads(f, params)
    assert any(g.abs().sum() > 0 for g in grads)
    g = torch.Generator().manual_seed(7)
    eps = 1e-6
    with torch.no_grad():
        # (1) two random directions through all parameters at once
        for _ in range(2):
            d = [torch.randn(p.shape, generator=g, dtype=p.dtype) for p in params]
            for p, di in zip(params, d):
                p.add_(eps * di)
            fp = float(f())
            for p, di in zip(params, d):
                p.sub_(2 * eps * di)
            fm = float(f())
            for p, di in zip(params, d):
                p.add_(eps * di)
            fd = (fp - fm) / (2 * eps)
            an = float(sum((gi * di).sum() for gi, di in zip(grads, d)))
            assert an == pytest.approx(fd, rel=1e-5, abs=1e-8)
        # (2) one coordinate in each of a few parameter tensors (stem, a block, a shortcut, the head)
        named = dict(net.named_parameters())
        picks = ["stem.0.weight", "stages.1.0.conv2.weight", "stages.2.0.shortcut.0.weight", "head.weight"]
        for name in picks:
            p = named[name]
            gp = grads[[id(q) for q in params].index(id(p))]
            flat = p.view(-1)
            i = int(torch.randint(flat.numel(), (1,), generator=g))
            old = float(flat[i])
            flat[i] = old + eps
            fp = float(f())
            flat[i] = old - eps
            fm = float(f())
            flat[i] = old
            assert float(gp.reshape(-1)[i]) == pytest.approx((fp - fm) / (2 * eps), rel=1e-4, abs=1e-7)


def test_exact_equals_explicit_loop_over_psi(setup):
    """‖M_b‖_F from the vmapped JVPs equals an explicit loop: full reverse-mode Jacobian ∂N/∂x times X_bj."""
    net, x, tangents, _, _ = setup
    pred, m = rendering_gradients(net, x, tangents)
    _, r = exact_regularizer(net, x, tangents)
    for b in range(B):
        jac = torch.autograd.functional.jacobian(lambda xb: net(xb[None])[0], x[b])  # (T, 3, H, W)
        rows = []
        for j in range(K):
            col = (jac * tangents[b, j]).sum(dim=(1, 2, 3))  # (T,) = (∂N/∂x)·X_bj
            torch.testing.assert_close(m[b, j], col, rtol=1e-10, atol=1e-12)
            rows.append(col)
        frob = torch.sqrt(sum((c * c).sum() for c in rows))
        assert float(r[b].detach()) == pytest.approx(float(frob), rel=1e-10)
    torch.testing.assert_close(pred, net(x))


def test_explicit_tangent_rules_match_functorch_jvp():
    """forward_tangents (explicit rules, every stem, max-pool and shortcuts) = vmap(jvp) to rounding."""
    for stem, h in (("small", 16), ("stride2", 32), ("imagenet", 64)):
        net = build_model(ModelConfig(out_dim=5, width=4, stem=stem), seed=2).double()
        g = torch.Generator().manual_seed(4)
        x = torch.randn(2, 3, h, h, generator=g, dtype=torch.float64)
        tangents = torch.randn(2, 3, 3, h, h, generator=g, dtype=torch.float64)
        p1, m1 = rendering_gradients(net, x, tangents, engine="functorch")
        p2, m2 = rendering_gradients(net, x, tangents, engine="explicit")
        torch.testing.assert_close(p2, p1, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(m2, m1, rtol=1e-10, atol=1e-12)


def test_stochastic_mean_matches_exact_squared_norm(setup):
    """E_v ‖M v‖² = ‖M‖_F² within the estimate's standard error (v ~ N(0, I_K), 2000 draws)."""
    net, x, tangents, _, _ = setup
    n = 2000
    _, r_exact = exact_regularizer(net, x[:1], tangents[:1])
    g = torch.Generator().manual_seed(3)
    v = torch.randn(n, K, generator=g, dtype=torch.float64)
    with torch.no_grad():
        _, r = stochastic_regularizer(net, x[:1].repeat(n, 1, 1, 1), tangents[:1].repeat(n, 1, 1, 1, 1), v)
    mean, se = float(r.mean()), float(r.std() / math.sqrt(n))
    target = float(r_exact[0].detach()) ** 2
    assert abs(mean - target) < 4 * se, (mean, target, se)
    # documented variance: Var = 2‖MᵀM‖_F²
    _, m = rendering_gradients(net, x[:1], tangents[:1])
    mm = (m[0] @ m[0].T).detach()  # (K, K) = MᵀM in our (K, T) layout
    assert float(r.var()) == pytest.approx(2 * float((mm * mm).sum()), rel=0.25)


def test_surrogate_is_norm_of_loss_gradient_wrt_psi(setup):
    """r_b = ‖∂ℓ_b/∂ψ‖ with ∂ℓ_b/∂ψ_j = sign(ŷ_b − y_b)ᵀ M_b[:, j] / T (chain rule through N)."""
    net, x, tangents, y, _ = setup
    pred, err, r = surrogate_regularizer(net, x, tangents, y)
    _, m = rendering_gradients(net, x, tangents)  # (B, K, T)
    s = torch.sign(pred - y) / T  # ∂ℓ/∂ŷ
    expected = torch.linalg.vector_norm(torch.einsum("bkt,bt->bk", m, s), dim=1)
    torch.testing.assert_close(r, expected, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(err, state_error(pred, y))


def test_calibrated_forms_share_one_scale(setup):
    """R_exact = c_T mean_b ‖M̃_b‖_F with M̃ = M diag(σ_ψ); the stochastic form squared, averaged over
    many draws of v, gives c_T² mean_b ‖M̃_b‖_F² (unbiased inner estimate); the surrogate is within a
    small factor of the exact form (equal in expectation over sign patterns)."""
    net, x, tangents, y, _ = setup
    scale = torch.tensor([0.5, 2.0, 1.3], dtype=torch.float64)
    assert SQRT_2_OVER_PI == pytest.approx(math.sqrt(2 / math.pi), rel=1e-15)  # E|z| of a standard normal
    c_t = math.sqrt(2 / math.pi) / math.sqrt(T)
    pred, m = rendering_gradients(net, x, tangents * scale.view(1, -1, 1, 1, 1))
    norms = torch.linalg.vector_norm(m.flatten(1), dim=1).detach()
    r_exact = risp_loss(net, x, y, "exact", 1.0, tangents, psi_scale=scale).reg
    assert float(r_exact) == pytest.approx(float(c_t * norms.mean()), rel=1e-10)
    g = torch.Generator().manual_seed(5)
    draws = torch.stack([risp_loss(net, x, y, "stochastic", 1.0, tangents, g, scale).reg for _ in range(3000)])
    assert float((draws**2).mean()) == pytest.approx(float(c_t**2 * (norms**2).mean()), rel=0.1)
    # the surrogate: √(2/π)·√T · mean_b ‖M̃_bᵀ sign(ŷ_b − y_b) / T‖, written out here (a lost √T or a wrong
    # constant in the code moves it by a factor of √T = 1.7 or more, which a ratio band alone would not see)
    r_surr = float(risp_loss(net, x, y, "surrogate", 1.0, tangents, psi_scale=scale).reg)
    per_b = torch.linalg.vector_norm(torch.einsum("bkt,bt->bk", m.detach(), torch.sign(pred.detach() - y) / T), dim=1)
    assert r_surr == pytest.approx(math.sqrt(2 / math.pi) * math.sqrt(T) * float(per_b.mean()), rel=1e-10)
    assert 1 / 3 < r_surr / float(r_exact) < 3  # and on the same scale as the exact form


def test_risp_loss_combines_terms(setup):
    net, x, tangents, y, _ = setup
    for reg in ("none", "surrogate", "exact", "stochastic"):
        terms = risp_loss(net, x, y, reg, 2.0, tangents, torch.Generator().manual_seed(0))
        assert float(terms.total.detach()) == pytest.approx(float((terms.error + 2.0 * terms.reg).detach()), rel=1e-12)
        assert (float(terms.reg) > 0) == (reg != "none")
    with pytest.raises(ValueError):
        risp_loss(net, x, y, "bogus", 1.0, tangents)


def test_instance_norm_values_and_no_torch_norm_modules():
    x = torch.randn(2, 4, 5, 6, dtype=torch.float64)
    torch.testing.assert_close(instance_norm(x), torch.nn.functional.instance_norm(x, eps=1e-5))
    net = ResNet18(ModelConfig(out_dim=9, width=8))
    kinds = {type(m) for m in net.modules()}
    assert InstanceNorm in kinds and torch.nn.SiLU in kinds
    assert not kinds & {torch.nn.InstanceNorm2d, torch.nn.BatchNorm2d, torch.nn.GroupNorm, torch.nn.ReLU}
    convs = [m for m in net.modules() if isinstance(m, torch.nn.Conv2d)]
    assert len(convs) == 1 + 16 + 3  # stem + 8 basic blocks × 2 + 3 projection shortcuts (ResNet-18)
    assert net(torch.randn(2, 3, 64, 64)).shape == (2, 9)
    with pytest.raises(ValueError, match="too small"):
        ResNet18(ModelConfig(out_dim=9, width=4, stem="imagenet"))(torch.randn(1, 3, 16, 16))


def test_automatic_stem_keeps_the_last_stage_at_least_4x4():
    """stem_for_resolution picks the coarsest stem whose last stage sees >= 4×4 pixels (instance norm of a 2×2 map
    keeps 2 numbers per channel): measured on the network's own feature map, not on the factors table."""
    from risp_train.model import stem_for_resolution

    def last_map(stem, res):
        net = ResNet18(ModelConfig(out_dim=3, width=4, stem=stem))
        return net.stages(net.stem(torch.randn(1, 3, res, res))).shape[-1]

    assert [stem_for_resolution(r) for r in (16, 32, 48, 64, 96, 128, 256)] == \
        ["small", "small", "small", "stride2", "stride2", "imagenet", "imagenet"]
    for res in (32, 64, 96, 128, 256):
        chosen = stem_for_resolution(res)
        assert last_map(chosen, res) >= 4
        coarser = {"small": "stride2", "stride2": "imagenet", "imagenet": None}[chosen]
        if coarser is not None:  # the next coarser stem would leave fewer than 4×4
            assert last_map(coarser, res) < 4


def test_input_normalization_chain_rule_matches_finite_differences():
    g = torch.Generator().manual_seed(5)
    image = torch.rand(2, 6, 6, 3, generator=g, dtype=torch.float64) * 3 + 0.01
    jac = torch.randn(2, 4, 6, 6, 3, generator=g, dtype=torch.float64)
    acc = StatsAccumulator(target_dim=2)
    acc.add(image, torch.randn(2, 2, generator=g))
    norm = acc.result()
    tang = norm.tangents(image, jac)  # (B, K, 3, H, W)
    eps = 1e-6
    for j in range(4):
        fd = (norm.images(image + eps * jac[:, j]) - norm.images(image - eps * jac[:, j])) / (2 * eps)
        torch.testing.assert_close(tang[:, j], fd, rtol=1e-6, atol=1e-8)
    # statistics: normalized images have zero mean, unit std per channel
    xn = norm.images(image)
    torch.testing.assert_close(xn.mean(dim=(0, 2, 3)), torch.zeros(3, dtype=torch.float64), atol=1e-9, rtol=0)
    torch.testing.assert_close(xn.std(dim=(0, 2, 3), unbiased=False), torch.ones(3, dtype=torch.float64))
    back = Normalization.from_dict(norm.to_dict())
    t = torch.randn(3, 2, dtype=torch.float64)
    torch.testing.assert_close(back.untargets(back.targets(t)), t)


def test_gamma_ramp():
    assert gamma_at(0, 100, 20.0, 0.5) == 0.0
    assert gamma_at(25, 100, 20.0, 0.5) == pytest.approx(10.0)
    assert gamma_at(50, 100, 20.0, 0.5) == 20.0
    assert gamma_at(99, 100, 20.0, 0.5) == 20.0
    assert gamma_at(0, 100, 20.0, 0.0) == 20.0


def test_gamma_start_delays_the_ramp():
    """γ = 0 before start · total, then the linear ramp over ramp_fraction of the steps after the start."""
    assert gamma_at(49, 100, 20.0, 0.5, 0.5) == 0.0
    assert gamma_at(50, 100, 20.0, 0.5, 0.5) == 0.0
    assert gamma_at(60, 100, 20.0, 0.5, 0.5) == pytest.approx(8.0)  # 10 of the 25 ramp steps
    assert gamma_at(75, 100, 20.0, 0.5, 0.5) == 20.0
    assert gamma_at(60, 200, 20.0, 0.5, 0.5) == 0.0
    assert gamma_at(10, 100, 20.0, 0.0, 0.3) == 0.0 and gamma_at(30, 100, 20.0, 0.0, 0.3) == 20.0


@pytest.mark.parametrize("env", ["quadrotor", "hand"])
def test_psi_scale_is_the_sampled_standard_deviation_in_each_domain(env):
    """σ_ψ against 20 000 draws of risp_data.psi.sample_rendering: the train domain's uniform ranges and the target
    domain's two-interval colours (a mixture whose σ is not the hull's (high − low)/√12)."""
    from risp_data.psi import psi_specs, sample_rendering
    from risp_train.regularizers import psi_scale

    for domain in ("train", "target"):
        rng = np.random.default_rng(7)
        psi = np.stack([sample_rendering(env, domain, rng).psi for _ in range(20_000)])
        np.testing.assert_allclose(psi_scale(env, domain).numpy(), psi.std(axis=0), rtol=0.02, err_msg=domain)
    hull = torch.tensor([(s.high - s.low) / 12 ** 0.5 for s in psi_specs(env, "target")], dtype=torch.float64)
    assert (psi_scale(env, "target")[2:] > 1.2 * hull[2:]).all()  # the colours' two intervals: wider than the hull's
