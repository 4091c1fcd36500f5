"""Rod simulator (docs/models/rod.md): the FEM energy's derivatives, the adjoint backward against finite
differences, the beam-theory sag check of issue 3, and clear errors for bad input."""

from __future__ import annotations

import pytest
import torch

from risp_data.envs import rod as geometry
from risp_data.errors import RispError
from risp_tasks.sims import _fem, get_simulator
from risp_tasks.sims.rod import _model, beam_theory_sag


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def sag_states():
    """Static equilibria under gravity for log10 E = 4, 5, 6, 7 (one batched Newton solve)."""
    sim = get_simulator("rod")
    params = torch.tensor([[4.0], [5.0], [6.0], [7.0]], dtype=torch.float64)
    return params, sim.equilibrium_state(params)


# -- finite elements ----------------------------------------------------------------------------------
def test_fem_gradient_and_hessian_match_autograd():
    grid = _fem.build_grid((0.0, 0.0, 0.0), (0.3, 0.2, 0.1), (3, 2, 2), torch.float64)
    gen = torch.Generator().manual_seed(0)
    x = grid.rest + 0.03 * torch.randn(grid.rest.shape, generator=gen, dtype=torch.float64)
    grad, He = _fem.energy_gradient(grid, x[None], 0.3, hessian=True)
    ref_grad = torch.autograd.functional.jacobian(lambda y: _fem.energy(grid, y[None], 0.3)[0], x)
    ref_hess = torch.autograd.functional.hessian(lambda y: _fem.energy(grid, y[None], 0.3)[0], x)
    torch.testing.assert_close(grad[0], ref_grad, rtol=1e-10, atol=1e-14)
    torch.testing.assert_close(_fem.assemble_dense(grid, He)[0], ref_hess.reshape(36, 36), rtol=1e-10, atol=1e-12)


def test_fem_energy_is_zero_at_rest_and_rotation_invariant():
    grid = _fem.build_grid((0.0, 0.0, 0.0), (0.3, 0.2, 0.1), (3, 2, 2), torch.float64)
    assert abs(float(_fem.energy(grid, grid.rest[None], 0.3))) < 1e-15
    gen = torch.Generator().manual_seed(1)
    x = grid.rest + 0.05 * torch.randn(grid.rest.shape, generator=gen, dtype=torch.float64)
    R = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))[0]
    R = R * torch.sign(torch.linalg.det(R))
    e1, e2 = _fem.energy(grid, x[None], 0.3), _fem.energy(grid, (x @ R.T + 0.7)[None], 0.3)
    torch.testing.assert_close(e1, e2, rtol=1e-12, atol=0)
    assert float(e1) > 0


def test_mesh_matches_environment_geometry():
    sim, m = get_simulator("rod"), _model(torch.float64)
    rest = sim.rest_state(2)
    assert rest.shape == (2, 360) and sim.action_dim == 1 and sim.param_names == ("log10_E",)
    torch.testing.assert_close(sim.to_env_state(rest), torch.full((2, 10), geometry.REST_HEIGHT, dtype=torch.float64))
    x_of_sensor = rest[0, m.sensor_index - 2]  # the x coordinate of the two centreline nodes per sensor
    torch.testing.assert_close(x_of_sensor, torch.tensor(geometry.SENSOR_X, dtype=torch.float64)[:, None].expand(10, 2))
    total_mass = float(m.mass.sum() / 3) + float(m.grid.node_volume[:6].sum() + m.grid.node_volume[-6:].sum()) * geometry.ROD_DENSITY
    assert abs(total_mass - geometry.ROD_DENSITY * geometry.ROD_LENGTH * geometry.ROD_WIDTH * geometry.ROD_THICKNESS) < 1e-9
    assert abs(float(m.load.sum()) - 1.0) < 1e-12


# -- physics ---------------------------------------------------------------------------------------------
def test_static_sag_falls_with_E_and_matches_beam_theory(sag_states):
    params, states = sag_states
    sag = geometry.REST_HEIGHT - get_simulator("rod").to_env_state(states).min(-1).values
    assert (sag[1:] < sag[:-1]).all() and (sag > 0).all()
    # small deflections (E = 10⁶, 10⁷ Pa): Euler–Bernoulli clamped–clamped w = qL⁴/(384 E I); one layer
    # of full-integration hexahedra is somewhat stiffer in bending (shear locking), hence the band
    for i in (2, 3):
        ratio = float(sag[i]) / beam_theory_sag(float(params[i, 0]))
        assert 0.6 < ratio < 1.1, ratio
    # linear elasticity scales as 1/E; geometric stiffening makes the soft rod sag less than that
    assert float(sag[2] / sag[3]) == pytest.approx(10.0, rel=0.05)
    assert float(sag[0] / sag[1]) < 10.0
    # symmetric about the centre
    z = get_simulator("rod").to_env_state(states)
    torch.testing.assert_close(z, z.flip(-1), rtol=0, atol=1e-9)


def test_equilibrium_is_a_fixed_point_of_the_dynamics(sag_states):
    sim = get_simulator("rod", ("rayleigh_damping",))
    params, states = sag_states
    params = torch.cat((params[1:3], torch.tensor([[1.0, 0.01], [0.0, 0.0]], dtype=torch.float64)), -1)
    out = sim.rollout(params, states[1:3], torch.zeros(2, 3, 1, dtype=torch.float64), 3)
    assert (out[:, -1] - states[1:3]).abs().max() < 1e-8


def test_centre_force_pushes_up_and_is_clamped():
    sim = get_simulator("rod")
    params = torch.tensor([[6.0]], dtype=torch.float64)
    s0 = sim.rest_state(3)
    forces = torch.tensor([[0.0], [400.0], [5000.0]], dtype=torch.float64)
    out = sim.to_env_state(sim.rollout(params.expand(3, 1), s0, forces[:, None, :].expand(3, 4, 1), 4))[:, -1]
    assert out[1, 4] > out[0, 4] + 1e-4  # the upward push lifts the centre
    lifted_max = sim.to_env_state(sim.rollout(params, s0[:1], torch.full((1, 4, 1), 600.0, dtype=torch.float64), 4))[0, -1]
    torch.testing.assert_close(out[2], lifted_max, rtol=0, atol=1e-6)  # 600 N and 5000 N both act as 500 N


def test_rayleigh_damping_removes_oscillation_energy(sag_states):
    params, states = sag_states
    s0 = states[1:2].clone()
    s0[:, 180:] += 0.5 * _model(torch.float64).ez  # kick: everything moves up at 0.5 m/s
    zero = torch.zeros(1, 15, 1, dtype=torch.float64)
    free = get_simulator("rod").rollout(params[1:2], s0, zero, 15)
    sim = get_simulator("rod", ("rayleigh_damping",))
    damped = sim.rollout(torch.tensor([[5.0, 5.0, 0.01]], dtype=torch.float64), s0, zero, 15)
    m = _model(torch.float64).mass

    def kinetic(s):
        return 0.5 * (m * s[..., 180:] ** 2).sum(-1)

    assert kinetic(damped[0, 1:]).sum() < 0.8 * kinetic(free[0, 1:]).sum()


# -- gradients (implicit-function-theorem adjoint) --------------------------------------------------------
def _random_case(sim, gen, batch=1, steps=3):
    params = sim.default_params(batch)
    params[:, 0] = 4.5 + torch.rand(batch, generator=gen, dtype=torch.float64)
    s0 = sim.equilibrium_state(params) + 0.003 * torch.randn(batch, 360, generator=gen, dtype=torch.float64)
    actions = 300 * torch.randn(batch, steps, 1, generator=gen, dtype=torch.float64)
    return params, s0, actions


def test_gradcheck_params_and_actions_with_rayleigh_damping():
    sim = get_simulator("rod", ("rayleigh_damping",))
    gen = torch.Generator().manual_seed(2)
    params, s0, actions = _random_case(sim, gen, steps=2)

    def f(p, a):
        return sim.to_env_state(sim.rollout(p, s0, a, 2))

    assert torch.autograd.gradcheck(f, (params.requires_grad_(), actions.requires_grad_()), rtol=1e-4)


def test_gradcheck_initial_state_fast_mode():
    sim = get_simulator("rod")
    gen = torch.Generator().manual_seed(3)
    params, s0, actions = _random_case(sim, gen, steps=2)

    def f(s):
        return sim.rollout(params, s, actions, 2)[:, -1]

    assert torch.autograd.gradcheck(f, (s0.requires_grad_(),), fast_mode=True, rtol=1e-4)


def test_directional_derivative_of_a_longer_rollout_matches_central_differences():
    sim = get_simulator("rod", ("rayleigh_damping",))
    gen = torch.Generator().manual_seed(4)
    steps = 8
    params, s0, actions = _random_case(sim, gen, batch=2, steps=steps)
    weights = torch.randn(2, steps + 1, 10, generator=gen, dtype=torch.float64)

    def loss(p, s, a):
        return (sim.to_env_state(sim.rollout(p, s, a, steps)) * weights).sum()

    inputs = [params.requires_grad_(), s0.requires_grad_(), actions.requires_grad_()]
    grads = torch.autograd.grad(loss(*inputs), inputs)
    eps = 1e-6
    with torch.no_grad():
        for k in range(3):
            direction = torch.randn(inputs[k].shape, generator=gen, dtype=torch.float64)
            plus = [x.detach().clone() for x in inputs]
            minus = [x.detach().clone() for x in inputs]
            plus[k] += eps * direction
            minus[k] -= eps * direction
            fd = (loss(*plus) - loss(*minus)) / (2 * eps)
            analytic = (grads[k] * direction).sum()
            assert float(abs(fd - analytic)) <= 1e-5 * float(abs(analytic)) + 1e-9, (k, float(fd), float(analytic))


def test_empty_batch_and_zero_steps():
    sim = get_simulator("rod")
    assert sim.rollout(sim.default_params(0), sim.rest_state(0), torch.zeros(0, 2, 1, dtype=torch.float64), 2).shape == (0, 3, 360)
    s0 = sim.rest_state(2)
    assert torch.equal(sim.rollout(sim.default_params(2), s0, torch.zeros(2, 0, 1, dtype=torch.float64), 0)[:, 0], s0)


def test_float32_and_batch_agree_with_float64():
    sim = get_simulator("rod")
    gen = torch.Generator().manual_seed(5)
    params, s0, actions = _random_case(sim, gen, batch=2, steps=4)
    ref = sim.rollout(params, s0, actions, 4)
    torch.testing.assert_close(sim.rollout(params[1:], s0[1:], actions[1:], 4)[0], ref[1], rtol=0, atol=1e-10)
    single = sim.rollout(params.float(), s0.float(), actions.float(), 4)
    assert single.dtype == torch.float32
    assert (sim.to_env_state(single).double() - sim.to_env_state(ref)).abs().max() < 1e-4
    p = params.float().requires_grad_()
    sim.to_env_state(sim.rollout(p, s0.float(), actions.float(), 4)).sum().backward()
    assert torch.isfinite(p.grad).all() and (p.grad != 0).all()


# -- bad input -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("case, fragment", [
    ("E_range", "log10_E"), ("nan", "log10_E"), ("negative", "rayleigh_damping.beta"),
    ("s0_shape", "s0"), ("no_actions", "actions"), ("dtype", "dtype"), ("half", "float32 or float64"),
])
def test_bad_input_names_the_argument(case, fragment):
    sim = get_simulator("rod", ("rayleigh_damping",))
    p, s0, a = sim.default_params(1), sim.rest_state(1), torch.zeros(1, 2, 1, dtype=torch.float64)
    if case == "E_range":
        p[0, 0] = 11.0
    elif case == "nan":
        p[0, 0] = float("nan")
    elif case == "negative":
        p[0, 2] = -1.0
    elif case == "s0_shape":
        s0 = s0[:, :180]
    elif case == "no_actions":
        a = None
    elif case == "dtype":
        a = a.float()
    elif case == "half":
        p, s0, a = p.half(), s0.half(), a.half()
    with pytest.raises(RispError, match=fragment):
        sim.rollout(p, s0, a, 2)
    with pytest.raises(RispError, match="states"):
        sim.to_env_state(torch.zeros(4, 10))


# -- the rendered range of the environment covers the documented (E, force) region ---------------------------
def test_simulated_states_stay_in_the_rendered_range():
    """docs/models/rod.md, "Rendered range": equilibria and rollouts from the sagged rod under a step
    force stay inside the risp_data environment's [state_low, state_high]."""
    from risp_data.envs import get_environment

    env, sim = get_environment("rod"), get_simulator("rod")
    low = torch.tensor(env.state_low, dtype=torch.float64)
    high = torch.tensor(env.state_high, dtype=torch.float64)

    def inside(z):
        return bool(((z >= low) & (z <= high)).all())

    # static equilibria over the whole documented region
    cases = [(e, f) for e in (5.0, 7.0) for f in (-500.0, 500.0)] + [(4.5, -300.0), (4.5, 300.0), (4.0, -100.0), (4.0, 100.0)]
    params = torch.tensor([[e] for e, _ in cases], dtype=torch.float64)
    force = torch.tensor([f for _, f in cases], dtype=torch.float64)
    eq = sim.equilibrium_state(params, force[:, None, None])
    assert inside(sim.to_env_state(eq))
    # rollouts: a ±200 N step at log10 E ∈ {5, 7} from the sagged rod, undamped (worst-case overshoot)
    params = torch.tensor([[5.0], [5.0], [7.0], [7.0]], dtype=torch.float64)
    actions = torch.tensor([200.0, -200.0, 200.0, -200.0], dtype=torch.float64)[:, None, None].expand(4, 80, 1)
    z = sim.to_env_state(sim.rollout(params, sim.equilibrium_state(params), actions, 80))
    assert inside(z)
    assert float(z[0].max()) > geometry.REST_HEIGHT + 0.2  # the test is not vacuous: the rod moves a lot


# -- the shared interface and the linear algebra's failure modes -------------------------------------------
def test_spec_declares_bounds_ranges_units_and_default_state():
    sim = get_simulator("rod", ("rayleigh_damping",))
    assert sim.param_bounds == ((3.0, 8.0), (0.0, float("inf")), (0.0, float("inf")))
    assert sim.spec.base_param_ranges == ((4.0, 7.0),) and sim.spec.base_param_units == ("log10 Pa",)
    assert sim.spec.available_effects["rayleigh_damping"].units == ("1/s", "s")
    torch.testing.assert_close(sim.rest_state(2), sim.default_state(2))
    torch.testing.assert_close(sim.to_env_state(sim.default_state(1)),
                               torch.full((1, 10), geometry.REST_HEIGHT, dtype=torch.float64))


def test_indefinite_hessian_is_shifted_in_newton_but_rejected_in_the_adjoint():
    from risp_tasks.sims.rod import _factor

    band = torch.zeros(2, 2, 4, dtype=torch.float64)
    band[:, 0] = torch.tensor([[2.0, 2.0, 2.0, 2.0], [2.0, -1e-6, 2.0, 2.0]])  # row 1: not positive definite
    _, shifts = _factor(band)
    assert shifts[0] == 0.0 and shifts[1] > 0.0  # the shift is reported
    with pytest.raises(RispError, match="not positive definite"):
        _factor(band, allow_shift=False)


def test_element_tables_live_on_their_grid():
    """Tables belong to the grid object (no cache keyed by id() that a new grid could reuse)."""
    for spacing in ((0.3, 0.2, 0.1), (0.1, 0.4, 0.25)):
        grid = _fem.build_grid((0.0, 0.0, 0.0), spacing, (3, 2, 2), torch.float64)
        G = grid.G
        lap = torch.kron(torch.einsum("qaj,qbj->ab", G, G) * grid.point_volume, torch.eye(3, dtype=torch.float64))
        torch.testing.assert_close(_fem.grid_laplacian(grid, torch.float64), lap)
        x = grid.rest + 0.02 * torch.randn(grid.rest.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
        _, He = _fem.energy_gradient(grid, x[None], 0.3, hessian=True)
        ref = torch.autograd.functional.hessian(lambda y: _fem.energy(grid, y[None], 0.3)[0], x)
        torch.testing.assert_close(_fem.assemble_dense(grid, He)[0], ref.reshape(36, 36), rtol=1e-10, atol=1e-12)
        del grid
