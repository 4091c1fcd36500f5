"""The task optimisation loop keeps the best iterate by the optimised loss (risp_tasks/tasks/loop.py)."""

import numpy as np
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


def _blows_up_beyond(limit: float):
    """c·x² inside |x| < limit, NaN outside: a step into a region the model cannot evaluate."""
    def loss(s):
        return torch.where(s.abs().max() < limit, (s ** 2).sum(), torch.full((), float("nan"), dtype=s.dtype))
    return loss


def test_a_nan_loss_mid_run_stops_there_and_keeps_the_best_iterate():
    """SGD with lr 3 on x² sends x from 1 to −5 to 25: the third loss is NaN.  The descent stops there (no step is
    taken from NaN), the best iterate (the start) is restored, and the stop is on record; the optimiser, whose state
    came from the bad step, is not handed on."""
    x, problem, _ = _quadratic(1.0, 1.0)
    h = optimize(problem, _blows_up_beyond(10.0), optimizer="sgd", lr=3.0, momentum=0.0, iterations=6, timer=Timer(),
                 progress=False)
    assert h["loss"] == pytest.approx([1.0, 25.0]) and len(h["seconds_per_iteration"]) == 2
    assert "iteration 2" in h["stopped"] and "best iterate (0" in h["stopped"]
    assert h["best_iteration"] == 0 and h["final_loss"] == pytest.approx(1.0) and h["last_loss"] != h["last_loss"]
    assert float(x.detach()) == pytest.approx(1.0) and h["optimizer"] is None


def test_a_nan_loss_at_the_start_is_a_clear_error():
    from risp_data.errors import RispError

    x, problem, _ = _quadratic(20.0, 1.0)
    with pytest.raises(RispError, match="NaN/inf at the start, before any optimisation step"):
        optimize(problem, _blows_up_beyond(10.0), optimizer="sgd", lr=0.1, momentum=0.0, iterations=3, timer=Timer(),
                 progress=False)


def test_a_continued_optimiser_is_one_descent():
    """``opt=`` continues an optimiser: 40 + 60 RMSProp iterations through one optimiser are bitwise the 100 of one
    call (a converging descent: no best-iterate restore).  A fresh RMSProp instead moves every coordinate by
    lr/sqrt(1 − α) = 10·lr on its first step whatever the gradient (its running mean of g² starts at 0), the kick
    that the warm start's hand-over avoids (docs/tasks.md §Warm start)."""
    from risp_tasks.tasks.loop import make_optimizer

    def run(x, problem, loss, n, opt=None):
        optimize(problem, loss, optimizer="rmsprop", lr=1e-3, momentum=0.0, iterations=n, timer=Timer(),
                 progress=False, opt=opt)
        return float(x.detach())

    x, problem, loss = _quadratic(1.0, 1.0)
    once = run(x, problem, loss, 100)
    y, problem_y, loss_y = _quadratic(1.0, 1.0)
    opt = make_optimizer("rmsprop", [y], 1e-3, 0.0)
    run(y, problem_y, loss_y, 40, opt)
    assert run(y, problem_y, loss_y, 60, opt) == once
    continued = once - run(y, problem_y, loss_y, 1, opt)
    fresh = once - run(x, problem, loss, 1)  # x is at the same point; a new optimiser takes the step
    assert fresh == pytest.approx(10 * 1e-3, rel=1e-6)
    assert 0 < continued < 0.2 * fresh


def test_horizon_grows_from_two_frames_to_all():
    from risp_tasks.tasks.loop import horizon

    assert [horizon(i, 6, 8) for i in range(8)] == [2, 3, 4, 5, 6, 7, 8, 8]
    assert [horizon(i, 0, 8) for i in range(3)] == [8, 8, 8]  # no curriculum
    assert [horizon(i, 4, 2) for i in range(3)] == [2, 2, 2]  # nothing to grow
    assert [horizon(i, 100, 20) for i in (0, 50, 99, 100)] == [2, 11, 19, 20]


def _line_fit(x0: float, frames: int):
    """s_t = x·t for t = 0 … T−1 against the reference t (x* = 1): the prefix loss over n frames is
    (x − 1)²·Σ_{t<n} t², so short horizons give *smaller* losses at the same x."""
    x = torch.tensor([x0], dtype=torch.float64, requires_grad=True)
    t = torch.arange(frames, dtype=torch.float64)
    problem = Problem(variables={"x": x}, states=lambda: (x * t).view(frames, 1), estimates=lambda: {"x": float(x)})

    def loss(s, n=None):
        n = frames if n is None else n
        return ((s[:n, 0] - t[:n]) ** 2).sum()
    return x, problem, loss


def test_the_curriculum_compares_growing_prefixes_and_keeps_only_full_horizon_iterates():
    from risp_tasks.tasks.loop import horizon

    x, problem, loss = _line_fit(3.0, 6)
    h = optimize(problem, loss, optimizer="sgd", lr=1e-3, momentum=0.0, iterations=8, timer=Timer(), progress=False,
                 grow=4, frames=6)
    assert h["frames_compared"] == [horizon(i, 4, 6) for i in range(8)] == [2, 3, 4, 5, 6, 6, 6, 6]
    # the first (two-frame) iterate has the lowest loss of the history, but it is not a full-horizon loss
    assert h["loss"][0] == min(h["loss"])
    assert h["best_iteration"] >= 4 and h["final_loss"] == pytest.approx(float(loss(problem.states().detach())))
    assert 1.0 < float(x.detach()) < 3.0  # it descended towards x* = 1


def test_a_curriculum_needs_the_frame_count():
    from risp_data.errors import RispError

    _, problem, loss = _line_fit(3.0, 6)
    with pytest.raises(RispError, match="number of compared frames"):
        optimize(problem, loss, optimizer="sgd", lr=1e-3, momentum=0.0, iterations=2, timer=Timer(), progress=False,
                 grow=2)


def test_the_state_loss_on_a_prefix_is_the_loss_of_those_frames():
    from risp_data.envs import get_environment
    from risp_tasks.tasks.loop import make_loss

    env = get_environment("quadrotor")
    g = torch.Generator().manual_seed(0)
    states = torch.randn(7, len(env.state_names), generator=g, dtype=torch.float64)
    keep = [0, 2, 4, 6]
    ref = env.state_to_target(torch.randn(4, len(env.state_names), generator=g, dtype=torch.float64))
    loss = make_loss("state", env, keep, ref, None, None)
    alone = make_loss("state", env, keep[:3], ref[:3], None, None)
    assert float(loss(states, 3)) == pytest.approx(float(alone(states)))
    assert float(loss(states, 3)) != pytest.approx(float(loss(states)))


@pytest.mark.parametrize("kw, message", [(dict(task="sysid", grow_horizon=-1), "--grow-horizon must be >= 0"),
                                         (dict(task="estimate", grow_horizon=5), "--grow-horizon is for sysid"),
                                         (dict(task="imitate", action_knots=1), "--action-knots must be 0"),
                                         (dict(task="sysid", action_knots=4), "--action-knots is for imitate"),
                                         (dict(task="sysid", params='{"mass": 3}'), "--params is for imitate")])
def test_a_bad_curriculum_or_knots_option_is_a_clear_error(kw, message):
    from risp_data.errors import RispError
    from risp_tasks.tasks.config import TaskConfig

    with pytest.raises(RispError, match=message):
        TaskConfig(video="v.mp4", **kw)


@pytest.mark.parametrize("given, message", [
    ('{"stiffness_index": 0.5, "nope": 1}', "unknown hand parameter 'nope'"),
    ('{"stiffness_index": NaN}', "'stiffness_index' must be a finite number"),
    ('{"stiffness_index": true}', "'stiffness_index' must be a finite number"),
    ('[0.5]', "must be a JSON object of parameter values"),
    ("stiff=0.5", "must be a JSON object of parameter values or a JSON file"),
    ('{"stiffness_index": 1/2}', "must be a JSON object of parameter values or a JSON file"),  # not "no such file"
])
def test_bad_params_are_one_clear_error(given, message):
    from risp_data.errors import RispError
    from risp_tasks.sims import get_simulator
    from risp_tasks.tasks.simulate import set_params

    sim = get_simulator("hand")
    with pytest.raises(RispError, match=message):
        set_params(sim, sim.default_params(), given)


def test_params_given_as_a_missing_path_or_a_result_folder(tmp_path):
    """A path that is not there says so (it used to be called "not a JSON object"); sysid's result folder — what it
    prints after "results:" — stands for its result.json; a folder without one is refused in one line."""
    import json

    from risp_data.errors import RispError
    from risp_tasks.sims import get_simulator
    from risp_tasks.tasks.simulate import read_params

    sim = get_simulator("hand")
    with pytest.raises(RispError, match=r"--params results/nosuch/result.json: no such file or folder"):
        read_params(sim, "results/nosuch/result.json")
    run = tmp_path / "sysid-v-seed0"
    run.mkdir()
    with pytest.raises(RispError, match=r"a folder without a result.json"):
        read_params(sim, str(run))
    (run / "result.json").write_text(json.dumps({"task": "sysid", "estimates": {"parameters": {"stiffness_index": 0.25}}}))
    assert read_params(sim, str(run)) == {"stiffness_index": 0.25}


def test_params_from_a_result_without_parameters_is_one_clear_error(tmp_path):
    """An imitate or estimate result.json has no ``estimates.parameters``: say so, instead of rejecting its
    ``task`` key as an unknown parameter."""
    import json

    from risp_data.errors import RispError
    from risp_tasks.sims import get_simulator
    from risp_tasks.tasks.simulate import set_params

    sim = get_simulator("hand")
    f = tmp_path / "result.json"
    f.write_text(json.dumps({"task": "imitate", "estimates": {"actions": "actions.csv"}}))
    with pytest.raises(RispError, match=r"result.json: --params: this imitate result holds no identified parameters"):
        set_params(sim, sim.default_params(), str(f))


def test_params_from_an_object_a_file_and_a_result(tmp_path):
    """The same values from a JSON object, a JSON file and a task's result.json; the rest stay nominal; the input
    is not changed."""
    import json

    from risp_tasks.sims import get_simulator
    from risp_tasks.tasks.simulate import set_params

    sim = get_simulator("hand")
    p0 = sim.default_params()
    a = set_params(sim, p0, '{"stiffness_ring": 0.25}')
    (tmp_path / "p.json").write_text('{"stiffness_ring": 0.25}')
    (tmp_path / "result.json").write_text(json.dumps({"task": "sysid", "estimates": {"parameters": {"stiffness_ring": 0.25}}}))
    for p in (a, set_params(sim, p0, str(tmp_path / "p.json")), set_params(sim, p0, str(tmp_path / "result.json"))):
        i = sim.param_index("stiffness_ring")
        assert float(p[0, i]) == 0.25 and torch.equal(torch.cat([p[0, :i], p[0, i + 1:]]), torch.cat([p0[0, :i], p0[0, i + 1:]]))
    assert float(p0[0, sim.param_index("stiffness_ring")]) == 1.0


@pytest.mark.parametrize("mode", ["state", "oracle"])
def test_the_l1_residual_sums_absolute_differences_in_target_space(mode):
    """--residual l1: mean_t Σ_j |τ_j(s_t) − goal_tj|, computed here by hand; l2 (the default) the squares; a
    residual outside {l2, l1} is one clear error."""
    from risp_data.envs import get_environment
    from risp_data.errors import RispError
    from risp_tasks.tasks.loop import make_loss

    env = get_environment("hand")
    g = torch.Generator().manual_seed(1)
    states = torch.randn(5, len(env.state_names), generator=g, dtype=torch.float64)
    keep = [0, 2, 4]
    goal = env.state_to_target(torch.randn(3, len(env.state_names), generator=g, dtype=torch.float64))
    ref, truth = (goal, None) if mode == "state" else (None, goal)
    r = env.state_to_target(states[keep]) - goal
    l1 = make_loss(mode, env, keep, ref, truth, None, residual="l1")
    l2 = make_loss(mode, env, keep, ref, truth, None)
    assert float(l1(states)) == pytest.approx(float(r.abs().sum(-1).mean()), rel=1e-12)
    assert float(l2(states)) == pytest.approx(float((r ** 2).sum(-1).mean()), rel=1e-12)
    assert float(l1(states)) != pytest.approx(float(l2(states)))
    # its gradient is sign(r) through τ: compare with autograd of the hand-written form
    s = states.clone().requires_grad_(True)
    l1(s).backward()
    s2 = states.clone().requires_grad_(True)
    (env.state_to_target(s2[keep]) - goal).abs().sum(-1).mean().backward()
    assert torch.allclose(s.grad, s2.grad)
    assert s.grad.abs().sum() > 0
    with pytest.raises(RispError, match="unknown residual 'l3'"):
        make_loss(mode, env, keep, ref, truth, None, residual="l3")


def test_an_unknown_residual_is_a_clear_error_in_the_config():
    from risp_data.errors import RispError
    from risp_tasks.tasks.config import TaskConfig

    with pytest.raises(RispError, match="unknown residual 'huber'; choose one of: l2, l1"):
        TaskConfig(task="imitate", video="v.mp4", residual="huber")
    assert TaskConfig(task="imitate", video="v.mp4").residual == "l2"


@pytest.mark.parametrize("task, loss, expected", [
    ("sysid", "state", "l1"), ("sysid", "render", "l1"), ("sysid", "oracle", "l1"),
    ("sysid", "pixelwise", "l2"), ("sysid", "perceptual", "l2"),
    ("imitate", "state", "l2"), ("imitate", "render", "l2"), ("control", "state", "l2"), ("estimate", "state", "l2"),
])
def test_the_default_residual_is_l1_in_sysid_only(task, loss, expected):
    """Without --residual, sysid's network-space losses are l1 and everything else l2 (docs/tasks.md §Residual
    norm); the resolved value is the config's (so result.json records it), and a given one is kept."""
    from risp_tasks.tasks.config import TaskConfig

    truth = "t.truth.json" if loss == "oracle" else None  # the oracle loss needs one (not read here)
    assert TaskConfig(task=task, video="v.mp4", loss=loss, truth=truth).residual == expected
    assert TaskConfig(task=task, video="v.mp4", loss=loss, truth=truth, residual="l2").residual == "l2"


def test_a_result_folder_has_the_usual_permissions(tmp_path):
    """Result folders are filled under a temporary name and renamed into place; they get the permissions of any
    folder the user makes (mkdtemp's 0700 would hide them from the other users of a shared machine)."""
    import os
    import stat

    from risp_tasks.tasks.results import ResultFolder

    old = os.umask(0o022)
    try:
        folder = ResultFolder(str(tmp_path / "res"))
        folder.write_json("result.json", {"seed": 0})
        out = folder.commit()
    finally:
        os.umask(old)
    assert stat.S_IMODE(os.stat(out).st_mode) == 0o755
    assert os.path.isfile(os.path.join(out, "result.json"))


def test_result_json_is_strict_json(tmp_path):
    """A non-finite number (the last iterate's loss after a diverging final step) is written as null: strict
    parsers (jq, JavaScript) read the file; arrays and tensors are lists."""
    import json
    import os

    import numpy as np
    import torch

    from risp_tasks.tasks.results import ResultFolder

    folder = ResultFolder(str(tmp_path / "res"))
    folder.write_json("result.json", {"last_loss": float("nan"), "final_loss": 0.5, "loss": [1.0, float("inf")],
                                      "x": np.arange(2), "t": torch.tensor([1.5]), "m": np.float64(2.0)})
    out = folder.commit()
    text = open(os.path.join(out, "result.json")).read()
    assert "NaN" not in text and "Infinity" not in text
    data = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-strict constant {c}"))
    assert data == {"last_loss": None, "final_loss": 0.5, "loss": [1.0, None], "x": [0, 1], "t": [1.5], "m": 2.0}


def test_the_summary_line_compares_full_horizon_losses():
    """With --grow-horizon the first losses compare fewer frames: the CLI's "loss A -> B" takes A from the first
    iteration over all frames, not the two-frame first loss."""
    from risp_tasks.cli import _loss_change

    grown = {"loss": [0.1, 0.5, 2.0, 1.5], "frames_compared": [2, 4, 6, 6], "final_loss": 1.2}
    assert _loss_change(grown) == "loss 2 (iteration 2, the first over all frames) -> 1.2"
    assert _loss_change({"loss": [3.0, 2.0], "final_loss": 1.5}) == "loss 3 -> 1.5"
    assert _loss_change({"loss": [], "final_loss": 1.5}) == "loss 1.5 -> 1.5"
    # a curriculum longer than the run: its last iterations still compare 5 of 10 frames, so none is "all frames"
    short = {"loss": [0.1, 0.3, 0.4], "frames_compared": [2, 3, 5], "frames_in_loss": 10, "final_loss": 0.9}
    assert _loss_change(short) == "loss 0.9 over all frames"


def test_the_no_improvement_note_under_a_curriculum(tmp_path, monkeypatch):
    """The CLI's note that no step improved names the first full-horizon iterate under --grow-horizon (best_iteration
    is never 0 there), and the start otherwise."""
    import risp_tasks.tasks.run as run_mod
    from click.testing import CliRunner
    from risp_tasks.cli import cli

    result = {"loss": [0.1, 0.5, 2.0, 2.5], "frames_compared": [2, 4, 6, 6], "frames_in_loss": 6, "final_loss": 2.0,
              "best_iteration": 2, "env": "hand", "out": "r", "estimates": {}, "config": {"warm_start": 0}}
    monkeypatch.setattr(run_mod, "run_task", lambda cfg, echo: result)
    out = CliRunner().invoke(cli, ["sysid", "v.mp4", "--quiet"]).output
    assert "note: no step improved on iteration 2, the first over all frames (loss 2)" in out, out
    result.update(best_iteration=3)
    assert "note:" not in CliRunner().invoke(cli, ["sysid", "v.mp4", "--quiet"]).output
    plain = {**result, "loss": [3.0, 4.0], "best_iteration": 0}
    del plain["frames_compared"], plain["frames_in_loss"]
    monkeypatch.setattr(run_mod, "run_task", lambda cfg, echo: plain)
    assert "note: no step improved on the start (loss 3)" in CliRunner().invoke(cli, ["sysid", "v.mp4", "--quiet"]).output


def test_estimate_csv_holds_the_mean_command_of_each_kept_interval():
    """With --every k, the trajectory CSV's command at a kept frame is the mean of the k per-frame commands it stands
    for (diagnose holds it until the next row), not the one row at that frame."""
    import numpy as np

    from risp_tasks.tasks.run import held_commands

    actions = np.arange(14, dtype=np.float64).reshape(7, 2)  # rows [0,1], [2,3], … [12,13]
    assert held_commands(actions, [0, 3, 6]).tolist() == [[2.0, 3.0], [8.0, 9.0], [12.0, 13.0]]
    assert held_commands(actions, list(range(7))).tolist() == actions.tolist()  # every frame kept: the rows


@pytest.mark.parametrize("task, shown, hidden", [
    ("estimate", ["--actions", "--every", "--source-fps"], ["--grow-horizon", "--action-knots", "--params"]),
    ("sysid", ["--actions", "--every", "--grow-horizon"], ["--action-knots", "--params"]),
    ("imitate", ["--action-knots", "--params", "--grow-horizon", "--every"], ["--actions"]),
    ("control", ["--action-knots", "--params", "--horizon"], ["--actions", "--every", "--source-fps", "--grow-horizon"]),
])
def test_each_tasks_help_lists_the_options_it_uses(task, shown, hidden):
    """A task's --help lists only the shared options it uses; the others stay accepted (hidden), so that the task
    can refuse them with a line saying whose they are (test_control_refuses_the_options_of_a_video)."""
    import re

    from click.testing import CliRunner
    from risp_tasks.cli import cli

    text = CliRunner().invoke(cli, [task, "--help"], terminal_width=200).output
    listed = set(re.findall(r"^\s+(--[a-z-]+)", text, flags=re.M))
    assert set(shown) <= listed and not set(hidden) & listed, sorted(listed)
    assert ("track" in text.split("--init")[1].split("\n")[0]) and ((task == "imitate") ==
                                                                     ("tracking controller" in text)), text


def test_loss_plot_marks_the_returned_iterate_at_result_json_s_index(tmp_path, monkeypatch):
    """loss.png's x axis counts the steps taken (0 = the start), the index of result.json's best_iteration: the
    star sits at that index (it was drawn one to the right, at best + 1)."""
    import risp_tasks.tasks.results as figure_module

    from risp_tasks.tasks.results import plot_loss

    figs = []
    real_save = figure_module.save_figure
    monkeypatch.setattr(figure_module, "save_figure", lambda fig, *a, **k: (figs.append(fig), real_save(fig, *a, **k)))
    history = [5.0, 3.0, 1.0, 2.0, 4.0]
    plot_loss(str(tmp_path / "loss.png"), history, "t", last=6.0, best=2, seed=0)
    (ax,) = figs[-1].axes
    stars = [ln for ln in ax.get_lines() if ln.get_marker() == "*"]
    assert len(stars) == 1 and list(stars[0].get_xdata()) == [2] and list(stars[0].get_ydata()) == [1.0]
    loss_line = next(ln for ln in ax.get_lines() if ln.get_label() == "loss")
    assert list(loss_line.get_xdata()) == [0, 1, 2, 3, 4]
    plot_loss(str(tmp_path / "loss2.png"), history, "t", last=0.5, best=5, seed=0)  # the last iterate returned
    stars = [ln for ln in figs[-1].axes[0].get_lines() if ln.get_marker() == "*"]
    assert list(stars[0].get_xdata()) == [5] and list(stars[0].get_ydata()) == [0.5]


def test_image_losses_render_with_the_runs_seed():
    """The image losses render every frame with the sampler seed ``render_seed`` (the run's --seed): the pixelwise
    loss equals the hand-written mean of (R(s; seed) − I)² with that seed, the same seed gives the same loss, and
    another seed other render noise (docs/tasks.md §Losses)."""
    from risp_data.diff_render import StateRenderer
    from risp_data.envs import get_environment
    from risp_tasks.tasks.loop import make_loss

    env = get_environment("cube")
    renderer = StateRenderer("cube", resolution=16, spp=1)
    rng = np.random.default_rng(3)
    states = torch.from_numpy(np.asarray(env.sample_states(rng, 2), np.float32))
    with torch.no_grad():
        ref = renderer(torch.from_numpy(np.asarray(env.sample_states(rng, 2), np.float32)), seed=11)
        by_seed = {s: float(make_loss("pixelwise", env, [0, 1], None, None, ref, renderer=renderer, render_seed=s)(states))
                   for s in (0, 5)}
        by_hand = float(((renderer(states, seed=5) - ref) ** 2).mean())
        again = float(make_loss("pixelwise", env, [0, 1], None, None, ref, renderer=renderer, render_seed=5)(states))
    assert by_seed[5] == pytest.approx(by_hand, rel=1e-6)
    assert again == by_seed[5]
    assert by_seed[0] != pytest.approx(by_seed[5], rel=1e-6)
