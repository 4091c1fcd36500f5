"""sysid --init scan: the start of the descent from a coarse scan of the state loss over the parameters' ranges
(risp_tasks.tasks.sysid.scan_start; docs/tasks.md §Scanned start)."""

import json
import os

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from tasks_helpers import shared_model, shared_video

pytestmark = pytest.mark.timeout(600)


def test_one_parameter_scan_finds_the_global_minimum_past_a_local_one():
    """A loss with a local minimum at x = 0.8 (the middle start's basin) and the global one at x = 0.25: the scan
    starts at the grid point nearest 0.25, where a descent from 0.5 would have rolled to 0.8."""
    from risp_tasks.tasks.sysid import SCAN_POINTS, scan_start

    def loss(s):  # s: (1, 1) "states" = the parameter itself
        x = float(s[0, 0])
        return torch.tensor(min(4 * (x - 0.25) ** 2, 0.05 + (x - 0.8) ** 2), dtype=torch.float64)

    x0, scanned = scan_start(loss, lambda x: x.view(1, 1).clone(), 1)
    assert x0.shape == (1,) and float(x0[0]) == pytest.approx(0.25)
    assert len(scanned["grid_x"]) == SCAN_POINTS and len(scanned["loss"]) == 1
    assert len(scanned["loss"][0]) == SCAN_POINTS
    assert scanned["grid_x"][0] == 0.0 and scanned["grid_x"][-1] == 1.0
    assert min(scanned["loss"][0]) == scanned["loss"][0][4]  # 4/16 = 0.25


def test_several_parameters_take_one_pass_of_coordinate_search():
    """A separable loss of three coordinates: one pass puts each on its own grid minimiser."""
    from risp_tasks.tasks.sysid import scan_start

    target = torch.tensor([0.125, 0.875, 0.5], dtype=torch.float64)
    calls = []

    def states_at(x):
        calls.append(x.clone())
        return x.view(1, -1).clone()

    x0, scanned = scan_start(lambda s: ((s[0] - target) ** 2).sum(), states_at, 3, points=9)
    assert torch.allclose(x0, target)
    assert len(calls) == 27 and len(scanned["loss"]) == 3
    assert all(float(c[1]) == 0.5 and float(c[2]) == 0.5 for c in calls[:9])  # the first sweep holds the others at ½
    assert all(float(c[0]) == 0.125 for c in calls[9:])  # later sweeps keep what the earlier ones chose


def test_a_loss_blind_to_a_parameter_leaves_it_in_the_middle():
    """Ties go to the grid point nearest the current value: a flat loss (e.g. the cube's contact stiffness in a
    clip without contact) keeps x = ½ rather than moving to the range's end, which bound_warnings would then call
    a bound the video asked for."""
    from risp_tasks.tasks.sysid import scan_start

    x0, _ = scan_start(lambda s: torch.tensor(1.0, dtype=torch.float64), lambda x: x.view(1, -1).clone(), 2)
    assert torch.equal(x0, torch.full((2,), 0.5, dtype=torch.float64))


def test_a_rollout_the_simulator_refuses_is_never_the_start():
    """The rod's Newton solve raises RispError where it cannot converge: that grid point counts as +inf, the scan
    goes on."""
    from risp_data.errors import RispError
    from risp_tasks.tasks.sysid import scan_start

    def states_at(x):
        if float(x[0]) < 0.2:
            raise RispError("rod: Newton's method did not converge")
        return x.view(1, 1).clone()

    x0, scanned = scan_start(lambda s: (s[0, 0] - 0.0) ** 2, states_at, 1)
    assert float(x0[0]) == pytest.approx(4 / 16) and scanned["loss"][0][:4] == [float("inf")] * 4


def test_a_nan_rollout_is_never_the_start_and_nan_everywhere_is_an_error():
    from risp_data.errors import RispError
    from risp_tasks.tasks.sysid import scan_start

    def loss(s):
        x = float(s[0, 0])
        return torch.tensor(float("nan") if x < 0.3 else (x - 0.2) ** 2, dtype=torch.float64)

    x0, scanned = scan_start(loss, lambda x: x.view(1, 1).clone(), 1)
    assert float(x0[0]) == pytest.approx(5 / 16)  # the first finite point past the NaNs, nearest 0.2
    assert scanned["loss"][0][0] == float("inf")
    with pytest.raises(RispError, match="not finite anywhere"):
        scan_start(lambda s: torch.tensor(float("nan")), lambda x: x.view(1, 1).clone(), 1)


def test_the_scan_with_the_real_quadrotor_lands_within_a_grid_step_of_the_true_mass():
    """The quadrotor simulator, commands a little above hover: the scan of an L1 trajectory loss against the
    trajectory of mass 2.93 kg picks the grid mass nearest it (grid step 0.025 kg)."""
    from risp_tasks.tasks.simulate import frame_states, timeline, to_sim_actions
    from risp_tasks.tasks.sysid import FreeParameters, scan_start

    sim, k = timeline("quadrotor", 10.0)
    n = 8
    file_actions = torch.full((n, 4), 3.0 * 9.81 / 4 * 1.1, dtype=torch.float64)
    s0 = sim.default_state(1)
    free = FreeParameters(sim, sim.default_params(), torch.tensor([0.5], dtype=torch.float64))

    def states_at(x):
        with torch.no_grad():
            free.x.copy_(x)
        p = free()
        return frame_states(sim, p, s0, to_sim_actions(sim, p, file_actions), n, k)

    true_x = (2.93 - 2.8) / 0.4
    truth = states_at(torch.tensor([true_x], dtype=torch.float64))
    x0, scanned = scan_start(lambda s: (s - truth).abs().sum(), states_at, 1)
    mass = 2.8 + 0.4 * float(x0[0])
    assert abs(mass - 2.93) <= 0.0125 + 1e-9, (mass, scanned)
    assert np.ptp(scanned["loss"][0]) > 0  # the loss sees the mass


@pytest.fixture(scope="module")
def quad(tmp_path_factory):
    return shared_model(tmp_path_factory, "quadrotor"), shared_video(tmp_path_factory, "quadrotor")


def _run(task, video, out, **kw):
    from risp_tasks.tasks.config import TaskConfig
    from risp_tasks.tasks.run import run_task

    return run_task(TaskConfig(task=task, video=video, out=str(out), progress=False, **kw), echo=lambda s: None)


def test_sysid_scan_starts_at_the_grid_point_of_least_state_loss(quad, tmp_path):
    """End to end: the start is the scanned grid's best point, the task's own first loss equals the scan's value
    there (the scan uses sysid's state loss), no worse than the middle start's, and the scan is in result.json and
    drawn in init_scan.png."""
    model, video = quad
    stem = os.path.splitext(video)[0]
    # --every 2: the scan compares the frames the descent does (a scan over every frame would not match r["loss"][0])
    kw = dict(model=model, actions=stem + ".actions.csv", truth=stem + ".truth.json", loss="state", iterations=1,
              every=2)
    r = _run("sysid", video, tmp_path / "scan", init="scan", **kw)
    scan = r["info"]["init_scan"]
    losses = np.asarray(scan["loss"][0])
    best = int(np.argmin(losses))
    assert scan["parameters"] == ["mass"] and len(scan["grid"][0]) == len(losses) == 17 and scan["seconds"] > 0
    assert best != 8  # the fixture's best point is not the middle start's, so the start below is the scan's doing
    assert r["initial"]["parameters"]["mass"] == pytest.approx(scan["grid"][0][best])
    true_mass = json.load(open(stem + ".truth.json"))["params"]["mass"]
    assert r["errors"]["parameter_error_initial"]["mass"] == pytest.approx(abs(scan["grid"][0][best] - true_mass))
    assert r["loss"][0] == pytest.approx(losses[best], rel=1e-9)
    d = _run("sysid", video, tmp_path / "middle", init="default", plots=False, **kw)
    assert d["loss"][0] == pytest.approx(losses[8], rel=1e-9) and r["loss"][0] <= d["loss"][0]
    assert os.path.isfile(tmp_path / "scan" / "init_scan.png")
    assert json.load(open(tmp_path / "scan" / "result.json"))["config"]["init"] == "scan"


@pytest.mark.parametrize("kw, message", [
    (dict(task="imitate"), "--init scan is sysid's"),
    (dict(task="estimate"), "--init scan is sysid's"),
    (dict(task="sysid", loss="pixelwise"), "--init scan scans the state loss"),
    (dict(task="sysid", loss="oracle", truth="t.json"), "--init scan scans the state loss"),
])
def test_scan_outside_sysid_or_with_a_loss_that_does_not_read_the_network_is_one_error(kw, message):
    from risp_data.errors import RispError
    from risp_tasks.tasks.config import TaskConfig

    with pytest.raises(RispError, match=message):
        TaskConfig(video="v.mp4", init="scan", **kw)


def test_render_mode_runs_its_warm_start_and_render_descent_from_the_scanned_start(quad, tmp_path):
    """--loss render --warm-start: the scan (state loss) sets the start, the warm start begins there (its first
    loss is the scan's least value), then one render iteration."""
    model, video = quad
    stem = os.path.splitext(video)[0]
    r = _run("sysid", video, tmp_path / "render", model=model, actions=stem + ".actions.csv", loss="render",
             init="scan", warm_start=2, iterations=1, spp=1, plots=False)
    assert r["warm_start"]["loss"][0] == pytest.approx(min(r["info"]["init_scan"]["loss"][0]), rel=1e-9)
    assert len(r["loss"]) == 1 and np.isfinite(r["final_loss"])


def test_the_cli_refuses_scan_for_imitate_in_one_line(tmp_path):
    from risp_tasks.cli import cli

    res = CliRunner().invoke(cli, ["imitate", str(tmp_path / "v.mp4"), "--init", "scan"])
    assert res.exit_code != 0
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "--init scan is sysid's" in lines[0], res.output


def test_the_hands_five_stiffnesses_take_one_coordinate_pass(tmp_path_factory, tmp_path):
    """The hand (five parameters): 5 × 17 rollouts; the start's loss is the last sweep's least value (every sweep
    keeps what the earlier ones chose) and no worse than the middle start's."""
    model, video = shared_model(tmp_path_factory, "hand"), shared_video(tmp_path_factory, "hand")
    stem = os.path.splitext(video)[0]
    kw = dict(model=model, actions=stem + ".actions.csv", loss="state", iterations=1, plots=False)
    r = _run("sysid", video, tmp_path / "scan", init="scan", **kw)
    scan = r["info"]["init_scan"]
    assert len(scan["parameters"]) == 5 and all(len(v) == 17 for v in scan["loss"])
    assert r["loss"][0] == pytest.approx(min(scan["loss"][-1]), rel=1e-9)
    for j, name in enumerate(scan["parameters"]):  # each coordinate sits on its sweep's best grid point
        assert r["initial"]["parameters"][name] == pytest.approx(scan["grid"][j][int(np.argmin(scan["loss"][j]))])
    d = _run("sysid", video, tmp_path / "middle", init="default", **kw)
    assert r["loss"][0] <= d["loss"][0] + 1e-12
