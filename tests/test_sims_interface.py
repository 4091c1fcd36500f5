"""The simulator interface (risp_tasks/sims/base.py), checked generically for every registered environment.

Every environment of risp_data has a simulator: a missing module or default state fails here, it is not skipped.
"""

from __future__ import annotations

import pytest
import torch

from risp_data.envs import ENV_NAMES
from risp_data.errors import RispError
from risp_tasks.sims import available_effects, get_simulator


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def _sim(env, effects=()):
    return get_simulator(env, effects)


def _inputs(sim, batch=2, steps=3, dtype=torch.float64):
    s0 = sim.default_state(batch, dtype)
    params = sim.default_params(batch, dtype)
    gen = torch.Generator().manual_seed(0)
    actions = None
    if sim.action_dim:
        actions = 0.1 * torch.rand(batch, steps, sim.action_dim, generator=gen, dtype=torch.float64).to(dtype)
        if sim.env == "quadrotor":
            actions = actions + sim.hover_actions(params, steps)
    return params, s0, actions


@pytest.mark.parametrize("env", ENV_NAMES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_shapes_and_dtypes(env, dtype):
    sim = _sim(env)
    params, s0, actions = _inputs(sim, dtype=dtype)
    states = sim.rollout(params, s0, actions, 3)
    assert states.shape == (2, 4, len(sim.state_names))
    assert states.dtype == dtype
    assert torch.equal(states[:, 0], s0)
    assert torch.isfinite(states).all()
    env_states = sim.to_env_state(states)
    assert env_states.shape[:2] == (2, 4) and env_states.dtype == dtype
    assert sim.rollout(params, s0, actions, 0).shape == (2, 1, len(sim.state_names))


@pytest.mark.parametrize("env", ENV_NAMES)
def test_rollout_matches_step(env):
    sim = _sim(env)
    params, s0, actions = _inputs(sim)
    states = sim.rollout(params, s0, actions, 3)
    s = s0
    for t in range(3):
        s = sim.step(params, s, None if actions is None else actions[:, t], t)
    assert torch.allclose(states[:, -1], s, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("env", ENV_NAMES)
def test_gradients_reach_params_state_actions(env):
    sim = _sim(env)
    params, s0, actions = _inputs(sim, dtype=torch.float32)
    leaves = [params.requires_grad_(), s0.requires_grad_()]
    if actions is not None:
        leaves.append(actions.requires_grad_())
    states = sim.rollout(params, s0, actions, 3)
    grads = torch.autograd.grad(states[:, -1].pow(2).sum(), leaves, allow_unused=True)
    for leaf, g in zip(("params", "s0", "actions"), grads):
        assert g is not None and torch.isfinite(g).all() and (g != 0).any(), leaf


@pytest.mark.parametrize("env", ENV_NAMES)
def test_effects_extend_params(env):
    base = _sim(env)
    effects = available_effects(env)
    assert set(effects) == set(base.spec.available_effects)
    for name, eff in effects.items():
        sim = get_simulator(env, (name,))
        names = sim.param_names
        assert names[: len(base.param_names)] == base.param_names
        assert names[len(base.param_names):] == tuple(f"{name}.{p}" for p in eff.param_names)
        assert len(eff.defaults) == len(eff.param_names) == len(eff.ranges)
        assert sim.default_params(3).shape == (3, len(names))
        for value, (lo, hi) in zip(eff.defaults, sim.param_bounds[len(base.param_names):]):
            assert lo <= value <= hi
        params, s0, actions = _inputs(sim)
        assert sim.rollout(params, s0, actions, 2).shape[-1] == len(sim.state_names)
    with pytest.raises(RispError, match="unknown effect"):
        get_simulator(env, ("no_such_effect",))


def test_unknown_environment():
    with pytest.raises(RispError, match="quadrotor"):
        get_simulator("blimp")


@pytest.mark.parametrize("env", ENV_NAMES)
def test_bad_input_names_the_argument(env):
    sim = _sim(env)
    params, s0, actions = _inputs(sim)
    with pytest.raises(RispError, match="params"):
        sim.rollout(params[:, :-1], s0, actions, 3)
    with pytest.raises(RispError, match="params"):
        sim.rollout(params[0], s0, actions, 3)
    with pytest.raises(RispError, match="s0"):
        sim.rollout(params, s0[:, :-1], actions, 3)
    with pytest.raises(RispError, match="steps"):
        sim.rollout(params, s0, actions, -1)
    bad = params.clone()
    bad[1, 0] = float("nan")
    with pytest.raises(RispError, match=sim.param_names[0]):
        sim.rollout(bad, s0, actions, 3)
    with pytest.raises(RispError):
        sim.rollout(params[:1], s0, actions, 3)  # batch sizes disagree
    if sim.action_dim:
        with pytest.raises(RispError, match="actions"):
            sim.rollout(params, s0, None, 3)
        with pytest.raises(RispError, match="actions"):
            sim.rollout(params, s0, actions[:, :, :-1], 3)
        nan_actions = actions.clone()
        nan_actions[0, 0, 0] = float("nan")
        with pytest.raises(RispError, match="actions"):
            sim.rollout(params, s0, nan_actions, 3)
    else:
        with pytest.raises(RispError, match="actions"):
            sim.rollout(params, s0, torch.zeros(2, 3, 1, dtype=params.dtype), 3)
