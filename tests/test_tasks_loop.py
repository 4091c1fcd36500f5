"""The task optimisation loop keeps the best iterate by the optimised loss (risp_tasks/tasks/loop.py)."""

import pytest
import torch

from risp_tasks.tasks.loop import Problem, Timer, optimize


def _quadratic(x0: float, curvature: float):
    x = torch.tensor([x0], dtype=torch.float64, requires_grad=True)
    problem = Problem(variables={"x": x}, states=lambda: x.view(1, 1), estimates=lambda: {"x": float(x)})
    return x, problem, lambda s: curvature * (s ** 2).sum()


def test_overshooting_steps_leave_the_best_iterate():
    """Plain gradient descent on c·x² with step lr > 1/c multiplies x by (1 − 2·lr·c) each step: |1 − 2·3| = 5,
    so every step is worse than the one before and the best point is the start."""
    x, problem, loss = _quadratic(1.0, 1.0)
    h = optimize(problem, loss, optimizer="sgd", lr=3.0, momentum=0.0, iterations=4, timer=Timer(), progress=False)
    assert h["loss"] == pytest.approx([1.0, 25.0, 625.0, 15625.0])
    assert h["last_loss"] == pytest.approx(390625.0)
    assert h["best_iteration"] == 0 and h["final_loss"] == pytest.approx(1.0)
    assert float(x.detach()) == pytest.approx(1.0)  # the variables were restored, not just the number reported


def test_a_late_overshoot_keeps_the_iterate_before_it():
    """Two good steps, then a momentum overshoot: the variables are those of the lowest loss seen."""
    x, problem, loss = _quadratic(1.0, 1.0)
    h = optimize(problem, loss, optimizer="sgd", lr=0.45, momentum=0.9, iterations=6, timer=Timer(), progress=False)
    best = min(h["loss"] + [h["last_loss"]])
    assert h["final_loss"] == pytest.approx(best) and h["final_loss"] < h["last_loss"]
    assert float(loss(x.detach().view(1, 1))) == pytest.approx(h["final_loss"])


def test_converging_descent_ends_at_the_last_iterate():
    x, problem, loss = _quadratic(1.0, 1.0)
    h = optimize(problem, loss, optimizer="sgd", lr=0.1, momentum=0.0, iterations=5, timer=Timer(), progress=False)
    assert h["best_iteration"] == 5 and h["final_loss"] == h["last_loss"] == pytest.approx(0.8 ** 10)
    assert float(x.detach()) == pytest.approx(0.8 ** 5)
