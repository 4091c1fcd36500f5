"""diagnose's OS failures are one `Error:` line naming the file (issue 13): an --out that cannot be a folder,
and a disk that fills while the report is written (nothing half-written is left)."""

from __future__ import annotations

import errno

import pytest
from click.testing import CliRunner

from risp_tasks.cli import cli
from risp_tasks.diagnose.synth import SynthConfig, make_synthetic


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    d = tmp_path_factory.mktemp("io") / "d"
    make_synthetic(SynthConfig(env="quadrotor", seed=3, n_traj=2, samples=120, effect="wind"), d)
    return d


def _run(data, out, *extra):
    return CliRunner().invoke(cli, ["diagnose", str(data), "--env", "quadrotor", "--out", str(out), "--effects", "wind",
                                    "--pairs-top", "0", "--max-iters", "3", "--quiet", *extra])


def _one_error_line(res):
    lines = [ln for ln in res.output.strip().splitlines() if ln.strip()]
    assert res.exit_code != 0 and len(lines) == 1 and lines[0].startswith("Error: "), res.output
    return lines[0]


def test_out_under_a_file_is_one_line_before_fitting(flights, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    line = _one_error_line(_run(flights, blocker / "report"))
    assert str(blocker) in line and "cannot write the report" in line


def test_disk_full_while_writing_the_report(flights, tmp_path, monkeypatch):
    import risp_tasks.diagnose.report as report

    def full(path, text):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(report, "write_text_atomic", full)
    out = tmp_path / "rep"
    line = _one_error_line(_run(flights, out, "--no-plots"))
    assert "report.json" in line and "No space left on device" in line
    assert not list(out.glob("report.*"))


@pytest.mark.parametrize("extra,words", [(["--max-segments", "0"], "--max-segments"),
                                         (["--rollout-horizon", "0"], "--rollout-horizon"),
                                         (["--seed", "-1"], "--seed must be in [0, 2**63)"),
                                         (["--seed", str(2 ** 64)], "--seed must be in [0, 2**63)"),  # was torch's
                                         (["--pairs-top", "-1"], "--pairs-top must be >= 0"),  # was "all but the last"
                                         (["--max-iters", "0"], "--max-iters must be >= 1"),  # named an unfitted cause
                                         (["--effects", ","], "--effects names no effect")])  # ran the base model alone
def test_out_of_range_counts_and_seed_are_one_line_and_leave_no_report(flights, tmp_path, extra, words):
    line = _one_error_line(_run(flights, tmp_path / "report", *extra))
    assert words in line
    assert not (tmp_path / "report").exists()


def test_diagnose_leaves_the_callers_torch_generator_as_it_was(flights, tmp_path):
    import torch

    torch.manual_seed(1234)
    expected = torch.rand(3)
    torch.manual_seed(1234)
    res = _run(flights, tmp_path / "report", "--seed", "7")
    assert res.exit_code == 0, res.output
    assert torch.equal(torch.rand(3), expected)  # without the fork, diagnose's manual_seed(7) would reseed it


def _with_sidecar(src, dst, **changes):
    """A copy of a synthetic folder whose sidecars get ``changes``."""
    import json
    import shutil

    shutil.copytree(src, dst)
    for side in dst.glob("*.json"):
        values = json.loads(side.read_text())
        if "env" in values:
            side.write_text(json.dumps({**values, **changes}))
    return dst


def test_a_misspelt_noise_group_is_one_line_and_leaves_no_folder(flights, tmp_path):
    """A declared noise group the model does not have ("positon") was silently estimated instead."""
    data = _with_sidecar(flights, tmp_path / "d", measurement_noise={"positon": 0.0005, "velocity": 0.01})
    line = _one_error_line(_run(data, tmp_path / "report"))
    assert "'positon', not a channel group of this model" in line and "position" in line, line
    assert not (tmp_path / "report").exists()


@pytest.mark.parametrize("extra, words", [(["--effects", "nosuch"], "unknown effect(s) nosuch"),
                                          (["--held-out", "1.5"], "held-out")])
def test_bad_options_found_after_reading_leave_no_folder(flights, tmp_path, extra, words):
    args = ["diagnose", str(flights), "--env", "quadrotor", "--out", str(tmp_path / "report"), "--quiet", *extra]
    line = _one_error_line(CliRunner().invoke(cli, args))
    assert words in line, line
    assert not (tmp_path / "report").exists()


def test_cube_gravity_other_than_the_simulators_is_refused(tmp_path):
    """docs/measured-data.md: diagnose refuses a gravity the simulator cannot represent; the cube's went unchecked."""
    d = tmp_path / "cube"
    make_synthetic(SynthConfig(env="cube", seed=1, n_traj=2, samples=60, effect=None), d)
    data = _with_sidecar(d, tmp_path / "g", gravity=5.0)
    line = _one_error_line(CliRunner().invoke(cli, ["diagnose", str(data), "--env", "cube", "--out",
                                                    str(tmp_path / "report"), "--quiet"]))
    assert "gravity 5.0 differs from the simulator's fixed 9.81" in line, line


def test_the_rods_gravity_is_checked_too():
    from risp_data.errors import RispError
    from risp_tasks.diagnose.candidates import check_supported
    from risp_tasks.measured import Sidecar

    check_supported("rod", Sidecar("rod", {"env": "rod", "gravity": 9.81}, "s.json"))
    with pytest.raises(RispError, match="s.json: gravity 5.0 differs from the simulator's fixed 9.81"):
        check_supported("rod", Sidecar("rod", {"env": "rod", "gravity": 5.0}, "s.json"))


def test_an_uncalibrated_floor_is_said_on_the_terminal(monkeypatch):
    """With the floor taken from the fitting part alone, a few short tosses may rest too briefly to calibrate it."""
    import risp_tasks.diagnose.run as run_mod

    report = {"cause": "friction", "reason": "r", "parameters": {}, "gain": {"normalized_rss": 0.1},
              "data": {"floor_calibration": {"applied": False, "mode": "auto", "rest_frames": 18}}}
    monkeypatch.setattr(run_mod, "diagnose", lambda cfg: report)
    out = CliRunner().invoke(cli, ["diagnose", "x.csv", "--env", "cube", "--out", "o", "--quiet"]).output
    assert "note: the floor was not calibrated: 18 resting frames in the fitting part, 20 needed" in out, out


def test_a_failed_rewrite_keeps_the_earlier_report_whole(flights, tmp_path, monkeypatch):
    """The report replaces --out as a whole: a disk that fills while the second report.md is written leaves the
    first run's report.json and report.md as they were (not a new report.json beside an old report.md), and no
    temporary folder behind."""
    import risp_tasks.diagnose.report as report

    out = tmp_path / "rep"
    assert _run(flights, out, "--no-plots").exit_code == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert set(before) == {"report.json", "report.md"}
    real = report.write_text_atomic

    def full_at_md(path, text):
        if str(path).endswith("report.md"):
            raise OSError(errno.ENOSPC, "No space left on device")
        real(path, text)

    monkeypatch.setattr(report, "write_text_atomic", full_at_md)
    line = _one_error_line(_run(flights, out, "--no-plots", "--seed", "1"))
    assert str(out / "report.md") in line and "No space left on device" in line
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rep"]


def test_an_out_folder_of_other_files_is_refused_before_fitting(flights, tmp_path):
    """--out naming a folder of the user's (not an earlier report) is one line and the folder is left alone,
    since the report replaces its folder whole."""
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    line = _one_error_line(_run(flights, out))
    assert "notes.txt" in line and "not a diagnose report" in line
    assert [p.name for p in out.iterdir()] == ["notes.txt"] and (out / "notes.txt").read_text() == "keep me"


def test_a_symlinked_out_is_written_through_and_a_file_browsers_ds_store_is_no_obstacle(flights, tmp_path):
    """--out as a symlink (or a mount point) cannot be replaced by a rename: the report is written into the folder
    it names, the link kept; a reused report folder holding .DS_Store (macOS's, from browsing it) is accepted."""
    target = tmp_path / "real"
    target.mkdir()
    link = tmp_path / "link"
    link.symlink_to(target, target_is_directory=True)
    res = _run(flights, link, "--no-plots")
    assert res.exit_code == 0, res.output
    assert link.is_symlink() and (target / "report.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "real"]  # no temporary left beside them
    (target / "ranking.png").write_bytes(b"an earlier report's plot")
    assert _run(flights, link, "--no-plots").exit_code == 0  # a rewrite: the earlier report's plots go
    assert not (target / "ranking.png").exists()
    (target / "keep.txt").write_text("mine")  # a folder of the user's behind the link: refused as any other
    line = _one_error_line(_run(flights, link, "--no-plots"))
    assert "keep.txt" in line and (target / "keep.txt").read_text() == "mine"
    out = tmp_path / "rep"
    assert _run(flights, out, "--no-plots").exit_code == 0
    (out / ".DS_Store").write_bytes(b"\0")
    assert _run(flights, out, "--no-plots", "--seed", "2").exit_code == 0
    assert '"seed": 2' in (out / "report.json").read_text()


def test_a_given_floor_offset_is_checked():
    """--floor-offset nan reached the simulator ('s0 contains NaN/inf'); 1e6 sank the cube 1000 km below the floor
    and a report was written.  NaN is refused with the options, a given offset by the reader's own rule."""
    from pathlib import Path

    from risp_data.errors import RispError
    from risp_tasks.diagnose.adapter import calibrate_floor
    from risp_tasks.diagnose.run import DiagnoseConfig, diagnose
    from risp_tasks.measured import load_measured

    tosses = Path(__file__).resolve().parents[1] / "risp_tasks" / "data" / "cube_tosses"
    with pytest.raises(RispError, match=r"--floor-offset must be 'auto' or a finite number of metres, got nan"):
        diagnose(DiagnoseConfig(data=(str(tosses),), env="cube", out=None, seed=0, floor_offset=float("nan")))
    trajs = load_measured([str(tosses)], "cube", limit=1)
    assert calibrate_floor(trajs, 0.001)[1] == {"applied": True, "mode": "given", "floor_offset_m": 0.001}
    with pytest.raises(RispError, match=r"--floor-offset 1e\+06: .* would go 1e\+06 m below the floor, more than a side"):
        calibrate_floor(trajs, 1e6)
