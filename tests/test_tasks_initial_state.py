"""The tasks' initial state s₀ (risp_tasks.tasks.simulate.InitialState): fixed from the network's first two
frames, or identified jointly (``--fit-initial-state``, the default where s₀ is read from the video)."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from risp_data.errors import RispError

pytestmark = pytest.mark.timeout(600)


def _ctx(env_name, predicted, fps=10.0, task="sysid"):
    from risp_data.envs import get_environment
    from risp_tasks.tasks.simulate import timeline

    sim, k = timeline(env_name, fps)
    return SimpleNamespace(sim=sim, env=get_environment(env_name), predicted=predicted, keep=list(range(len(predicted))),
                           fps=fps, k=k, cfg=SimpleNamespace(task=task))


def _quad_estimates():
    # N's estimates of two frames 0.1 s apart: x, y, z [m], yaw, pitch, roll [rad]
    return torch.tensor([[0.05, -0.10, 1.10, 0.30, 0.05, -0.04],
                         [0.08, -0.12, 1.14, 0.32, 0.06, -0.02]], dtype=torch.float64)


def test_fixed_initial_state_is_the_networks_first_frames():
    from risp_tasks.tasks.simulate import InitialState, initial_sim_state

    ctx = _ctx("quadrotor", _quad_estimates())
    s0 = InitialState(ctx, fit=False)
    assert s0.variables == {}
    expected = initial_sim_state(ctx.sim, ctx.predicted[0], ctx.predicted[1], ctx.fps)
    assert torch.equal(s0(), expected)
    # velocity from the difference of the two estimates: (0.03, −0.02, 0.04) m per 0.1 s
    assert np.allclose(expected[0, 7:10].numpy(), [0.3, -0.2, 0.4])


def test_fitted_initial_state_starts_at_the_estimates_and_its_gradient_matches_central_differences():
    """d/dx of a rollout loss through s₀(x) (pose of frame 0, linear velocity from frames 0 and 1, body angular
    velocity from the second row's angle entries), float64, against central differences on every offset."""
    from risp_tasks.tasks.simulate import InitialState, action_centre, frame_states

    ctx = _ctx("quadrotor", _quad_estimates())
    s0 = InitialState(ctx, fit=True)
    x = s0.variables["initial_state"]
    assert x.shape == (2, 6) and x.dtype == torch.float64
    assert torch.equal(s0().detach(), InitialState(ctx, fit=False)())  # x = 0: the network's estimates
    params = ctx.sim.default_params()
    goal = torch.tensor([0.1, -0.2, 1.2, 0.2, 0.0, 0.1], dtype=torch.float64)
    hover = action_centre(ctx.sim, params).expand(4, -1) * torch.tensor([1.02, 0.98, 1.01, 0.99])

    def loss():
        states = frame_states(ctx.sim, params, s0(), hover, 4, ctx.k)
        return ((states - goal) ** 2).sum()

    with torch.no_grad():
        x.copy_(torch.tensor([[0.2, -0.1, 0.3, 0.1, -0.2, 0.15], [-0.1, 0.25, 0.05, -0.3, 0.1, 0.2]]))
    (grad,) = torch.autograd.grad(loss(), x)
    h, fd = 1e-6, torch.zeros_like(x)
    with torch.no_grad():
        for idx in np.ndindex(*x.shape):
            x[idx] += h
            up = loss()
            x[idx] -= 2 * h
            down = loss()
            x[idx] += h
            fd[idx] = (up - down) / (2 * h)
    assert torch.allclose(grad, fd, rtol=1e-5, atol=1e-7), (grad, fd)
    assert grad.abs().min() > 0  # every offset moves the rollout (pose, linear and angular velocity)
    with torch.no_grad():  # the second row's angle entries are the body angular velocity [rad/s]
        assert np.allclose(s0()[0, 10:13].numpy(), 1.0 * x[1, 3:6].numpy())
    info = s0.info()
    assert info["initial_state_fitted"] is True
    offsets = np.asarray(info["initial_state_offsets"])  # what s₀ uses: σ ⊙ x, the second row's angles ω₀ in rad/s
    assert np.allclose(offsets[0], (s0.step * x[0]).detach().numpy())
    assert np.allclose(offsets[1, :3], (s0.step[:3] * x[1, :3]).detach().numpy())
    assert np.allclose(offsets[1, 3:6], s0()[0, 10:13].detach().numpy())


def test_default_fits_where_the_video_gives_the_initial_state_and_the_rod_keeps_rest():
    from risp_tasks.tasks.simulate import InitialState

    assert InitialState(_ctx("quadrotor", _quad_estimates())).fit is True
    from risp_data.envs import get_environment

    n = len(get_environment("hand").state_names)
    hand = InitialState(_ctx("hand", torch.zeros(2, n, dtype=torch.float64)))
    assert hand.fit is True and hand.variables["initial_state"].shape == (2, n)
    rod = InitialState(_ctx("rod", torch.zeros(2, 10, dtype=torch.float64)))
    assert rod.fit is False and rod.variables == {}
    with pytest.raises(RispError, match="rod"):
        InitialState(_ctx("rod", torch.zeros(2, 10, dtype=torch.float64)), fit=True)


def test_fit_initial_state_is_refused_for_estimate_and_control():
    from risp_tasks.tasks.config import TaskConfig

    for task in ("estimate", "control"):
        with pytest.raises(RispError, match="fit-initial-state"):
            TaskConfig(task=task, video="v.mp4", fit_initial_state=True)
    TaskConfig(task="control", video="v.png")  # the default (None) is fine for every task


def test_control_warns_of_an_initial_state_outside_the_trained_range():
    """control --initial-state far outside the box the training states were drawn from: a warning naming the
    states that leave it; inside the box (and the simulator's default state): none."""
    from risp_tasks.sims import get_simulator
    from risp_tasks.tasks.control import initial_state_warning
    from risp_tasks.tasks.simulate import initial_sim_state

    sim = get_simulator("quadrotor")
    inside = initial_sim_state(sim, torch.tensor([0.05, -0.1, 1.1, 0.3, 0.05, -0.04], dtype=torch.float64), None, 1.0)
    assert initial_state_warning(sim, inside, "s0.json") is None
    assert initial_state_warning(sim, sim.default_state(1, torch.float64), "s0.json") is None
    far = initial_sim_state(sim, torch.tensor([5.0, -0.1, 1.1, 0.3, 0.05, 1.2], dtype=torch.float64), None, 1.0)
    warning = initial_state_warning(sim, far, "s0.json")
    assert warning.startswith("s0.json: the initial state's") and "x, roll" in warning and "y" not in warning.split("state's")[1][:4]
