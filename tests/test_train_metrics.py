"""risp-train eval's per-group metrics on hand-built predictions with known errors (issue 8, item 3)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from risp_data.errors import RispError
from risp_train.evaluate import STATE_GROUPS, geodesic_angle_deg, group_errors, markdown_table, summarize_groups


def _rigid_truth(n=5):
    rng = np.random.default_rng(0)
    p = rng.uniform(-0.3, 0.3, (n, 3))
    e = np.c_[rng.uniform(-math.pi, math.pi, n), rng.uniform(-1.2, 1.2, n), rng.uniform(-math.pi, math.pi, n)]
    return np.c_[p, e]


@pytest.mark.parametrize("env", ["quadrotor", "cube"])
def test_position_and_attitude_errors_are_known_offsets(env):
    """Position off by (0.03, 0.04, 0) m → 0.05 m; a pure yaw offset of 10° on a level body → 10°."""
    true = _rigid_truth()
    true[:, 4:6] = 0.0  # level: a yaw offset is then a rotation by exactly that angle
    pred = true.copy()
    pred[:, 0] += 0.03
    pred[:, 1] += 0.04
    pred[:, 3] += math.radians(10.0)
    err = group_errors(env, pred, true)
    assert set(err) == {"position", "attitude"}
    np.testing.assert_allclose(err["position"], 0.05, atol=1e-12)
    np.testing.assert_allclose(err["attitude"], 10.0, atol=1e-6)


def test_geodesic_angle_is_independent_of_the_euler_representation():
    """(yaw, pitch, roll) and (yaw + π, π − pitch, roll + π) are the same rotation: 0°; a rotation by 30°
    about the body's x axis (roll + 30°) is 30° whatever the rest of the pose; wrap-around is 0°."""
    true = _rigid_truth(20)
    same = true.copy()
    same[:, 3:6] = np.c_[true[:, 3] + math.pi, math.pi - true[:, 4], true[:, 5] + math.pi]
    np.testing.assert_allclose(geodesic_angle_deg(same[:, 3:6], true[:, 3:6]), 0.0, atol=1e-5)
    rolled = true[:, 3:6].copy()
    rolled[:, 2] += math.radians(30.0)
    np.testing.assert_allclose(geodesic_angle_deg(rolled, true[:, 3:6]), 30.0, atol=1e-6)
    wrapped = true[:, 3:6] + np.array([2 * math.pi, 0.0, -2 * math.pi])
    np.testing.assert_allclose(geodesic_angle_deg(wrapped, true[:, 3:6]), 0.0, atol=1e-5)
    flipped = true[:, 3:6].copy()
    flipped[:, 0] += math.pi  # yaw by 180° about world z: 180°
    np.testing.assert_allclose(geodesic_angle_deg(flipped, true[:, 3:6]), 180.0, atol=1e-4)


def test_joint_and_sensor_errors_are_mean_absolute_errors():
    rng = np.random.default_rng(1)
    hand = rng.uniform(-0.7, 0.7, (4, 13))
    offsets = np.where(np.arange(13) % 2 == 0, 0.1, -0.1)
    np.testing.assert_allclose(group_errors("hand", hand + offsets, hand)["joints"], 0.1, atol=1e-12)
    rod = rng.uniform(0.3, 1.5, (4, 10))
    offsets = np.r_[np.full(5, 0.02), np.full(5, -0.04)]
    np.testing.assert_allclose(group_errors("rod", rod + offsets, rod)["sensors"], 0.03, atol=1e-12)


def test_summary_and_table_report_mean_std_count_and_units():
    true = _rigid_truth(4)
    pred = true.copy()
    pred[:2, 2] += 0.1  # two images 0.1 m off, two exact: mean 0.05, std 0.05
    s = summarize_groups("cube", pred, true)
    assert s["position"] == {"mean": pytest.approx(0.05), "std": pytest.approx(0.05), "n": 4, "unit": "m"}
    assert s["attitude"]["unit"] == "deg" and s["attitude"]["mean"] == pytest.approx(0.0, abs=1e-5)
    result = {"metric": "l1", "shards": "x", "env": "cube", "domain": "target", "n": 4,
              "results": {"model": {"mean": 0.2, "std": 0.1}, "average": {"mean": 0.5, "std": 0.2}},
              "groups": {"model": s, "average": s}}
    table = markdown_table(result)
    assert "position [m]" in table and "attitude [deg]" in table and "n = 4" in table
    assert "0.0500 ± 0.0500" in table and "0.2000 ± 0.1000" in table
    assert set(STATE_GROUPS) == {"quadrotor", "cube", "hand", "rod"}


def test_paper_l1_and_l2_on_a_hand_built_difference():
    """state_differences wraps the angles to (−π, π] and only them; per_image_error is the mean absolute
    difference (l1, the paper's) or the Euclidean norm (l2) of a row — on a case worked out by hand."""
    from risp_train.evaluate import per_image_error, state_differences

    names = ("x", "y", "z", "yaw", "pitch", "roll")
    deg = np.pi / 180
    pred = np.array([[1.0, 0.0, 0.5, 179 * deg, 0.0, np.pi], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    true = np.array([[0.0, 3.0, 0.5, -179 * deg, 0.1, -np.pi], [0.0, 0.0, 4.0, 0.0, 0.0, 3 * np.pi / 2]])
    d = state_differences(pred, true, names)
    expected = np.array([[1.0, -3.0, 0.0, -2 * deg, -0.1, 0.0],  # 358° is a 2° error; π − (−π) is none
                         [0.0, 0.0, -4.0, 0.0, 0.0, np.pi / 2]])  # −3π/2 wraps to +π/2; z (metres) is not wrapped
    np.testing.assert_allclose(d, expected, atol=1e-12)
    assert state_differences(np.array([[0.0, 0, 0, np.pi, 0, 0]]), np.zeros((1, 6)), names)[0, 3] == pytest.approx(np.pi)
    assert state_differences(np.array([[0.0, 0, 0, -np.pi, 0, 0]]), np.zeros((1, 6)), names)[0, 3] == pytest.approx(np.pi)
    np.testing.assert_allclose(per_image_error(d, "l1"), [(1 + 3 + 2 * deg + 0.1) / 6, (4 + np.pi / 2) / 6], rtol=1e-12)
    np.testing.assert_allclose(per_image_error(d, "l2"), [np.sqrt(1 + 9 + (2 * deg) ** 2 + 0.01),
                                                          np.sqrt(16 + np.pi ** 2 / 4)], rtol=1e-12)
    with pytest.raises(RispError, match="unknown --metric"):
        per_image_error(d, "l3")


def test_scatter_plot_draws_attitude_in_degrees_with_units(tmp_path, monkeypatch):
    """eval's predicted-vs-true PNG: angles in degrees, as its tables report them, and each panel names its unit
    (the yaw/pitch/roll panels were radians without a unit beside a table in degrees)."""
    import risp_train.plots as figure_module

    from risp_train.plots import plot_predicted_vs_true

    figs = []
    real_save = figure_module.save_figure
    monkeypatch.setattr(figure_module, "save_figure", lambda fig, *a, **k: (figs.append(fig), real_save(fig, *a, **k)))
    true = _rigid_truth(4)
    pred = true + 0.01
    names = ["x", "y", "z", "yaw", "pitch", "roll"]
    plot_predicted_vs_true(pred, true, names, str(tmp_path / "s.png"), units=["m"] * 3 + ["deg"] * 3, seed=4)
    axes = [ax for ax in figs[-1].axes if ax.get_title()]
    assert [ax.get_title() for ax in axes] == ["x [m]", "y [m]", "z [m]", "yaw [°]", "pitch [°]", "roll [°]"]
    yaw_points = axes[3].collections[0].get_offsets()
    np.testing.assert_allclose(np.asarray(yaw_points)[:, 0], np.degrees(true[:, 3]))
    x_points = axes[0].collections[0].get_offsets()
    np.testing.assert_allclose(np.asarray(x_points)[:, 0], true[:, 0])


def test_loss_plot_leaves_out_the_steps_before_the_regularizer_starts(tmp_path, monkeypatch):
    """losses.png: the steps whose logged regularizer is 0 (γ not started: not computed) are not drawn at the log
    axis' floor as if they were values; the computed ones are drawn as logged."""
    import csv

    import risp_train.plots as figure_module

    from risp_train.plots import plot_losses

    rows = [(s, 1.0 / (s + 1), 0.0 if s < 5 else 0.2 + 0.01 * s) for s in range(10)]
    path = tmp_path / "losses.csv"
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["step", "epoch", "batch", "lr", "gamma", "loss", "error", "reg", "seconds"])
        for s, e, r in rows:
            w.writerow([s, 0, s, 1e-3, 0.3, e + r, e, r, 0.1])
    figs = []
    real_save = figure_module.save_figure
    monkeypatch.setattr(figure_module, "save_figure", lambda fig, *a, **k: (figs.append(fig), real_save(fig, *a, **k)))
    plot_losses(str(path), str(tmp_path / "losses.png"), reg="stochastic", seed=4)
    (line,) = figs[-1].axes[1].get_lines()
    assert list(line.get_xdata()) == list(range(5, 10))
    np.testing.assert_allclose(line.get_ydata(), [r for _, _, r in rows[5:]])
    from risp_data.figures import png_provenance

    # the PNG names its run's seed (its JSON beside it does too)
    assert png_provenance(tmp_path / "losses.png") == {"Software": "risp", "risp:seed": "4",
                                                       "risp:what": "risp-train fit: loss curves"}


def test_plots_leave_the_callers_matplotlib_backend_alone(tmp_path):
    """Every plot called matplotlib.use("Agg"): a notebook user who ran an evaluation or a diagnosis from Python
    was switched to Agg, and plt.show() showed nothing afterwards.  The figures are drawn without pyplot."""
    import matplotlib

    from risp_tasks.tasks.results import plot_loss, plot_trajectories
    from risp_train.plots import plot_predicted_vs_true

    before = matplotlib.get_backend()
    try:
        matplotlib.use("svg")  # a backend the plots must not replace (any non-Agg one)
        plot_loss(str(tmp_path / "loss.png"), [3.0, 2.0, 1.0], "t", seed=0)
        plot_trajectories(str(tmp_path / "traj.png"), ["x"], None, {"a": (np.arange(3.0), np.zeros((3, 1)))}, seed=0)
        true = _rigid_truth(3)
        plot_predicted_vs_true(true + 0.01, true, ["x", "y", "z", "yaw", "pitch", "roll"], str(tmp_path / "s.png"),
                               seed=0)
        assert matplotlib.get_backend() == "svg"
        assert all((tmp_path / n).stat().st_size > 1000 for n in ("loss.png", "traj.png", "s.png"))
    finally:
        matplotlib.use(before)
