"""Measured-data reading and validation (risp_tasks.measured): formats, sidecars and clear errors."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from risp_data.errors import RispError
from risp_tasks.measured import body_rates_from_quat, load_measured, write_trajectory_csv

# The project's shared data beside the checkout (CI), else the 12 tosses bundled with the package.
CUBE_TOSSES = Path(__file__).resolve().parents[2] / "shared" / "data" / "cube-tosses"
if not CUBE_TOSSES.is_dir():
    CUBE_TOSSES = Path(__file__).resolve().parents[1] / "risp_tasks" / "data" / "cube_tosses"


def _rotation_trajectory(n=40, dt=0.01, with_vel=True):
    """A cube spinning about a tilted axis while flying a parabola: known velocities."""
    t = np.arange(n) * dt
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    rate = 2.0  # rad/s about a fixed axis: body rates = world rates = rate·axis
    ang = rate * t
    q = np.concatenate([np.cos(ang / 2)[:, None], np.sin(ang / 2)[:, None] * axis], 1)
    pos = np.stack([0.5 * t, -0.2 * t, 0.5 + 1.0 * t - 4.905 * t**2], 1)
    cols = {"t": t, "x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2],
            "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3]}
    if with_vel:
        cols.update(vx=np.full(n, 0.5), vy=np.full(n, -0.2), vz=1.0 - 9.81 * t,
                    wx=np.full(n, rate * axis[0]), wy=np.full(n, rate * axis[1]), wz=np.full(n, rate * axis[2]))
    return cols, rate * axis


CUBE_SIDECAR = {"env": "cube", "side": 0.1048, "mass": 0.37}


def _write(tmp_path, cols, sidecar=CUBE_SIDECAR, name="traj.csv"):
    p = tmp_path / name
    write_trajectory_csv(p, cols, sidecar)
    return p


def test_real_cube_tosses_load_with_default_sidecar():
    trajs = load_measured([str(CUBE_TOSSES)], "cube", limit=3)
    assert len(trajs) == 3
    tr = trajs[0]
    assert tr.sidecar.values["side"] == pytest.approx(0.1048)
    if not (CUBE_TOSSES / "sidecar.json").exists():  # the shared folder has no sidecar: README defaults
        assert "ContactNets" in tr.sidecar.source
    assert tr.dt == pytest.approx(1 / 148, rel=1e-3)
    assert np.allclose(np.linalg.norm(tr.quat, axis=1), 1.0)
    assert not tr.vel_estimated


def test_side_override_and_unit_mistake():
    trajs = load_measured([str(CUBE_TOSSES / "toss_000.csv")], "cube", overrides={"side": 0.105, "mass": 0.4})
    assert trajs[0].sidecar.values["side"] == 0.105
    with pytest.raises(RispError, match=r"--side 104.8: .*unit"):  # the option, not the file's key
        load_measured([str(CUBE_TOSSES / "toss_000.csv")], "cube", overrides={"side": 104.8})


def test_velocities_estimated_when_absent(tmp_path):
    cols, omega = _rotation_trajectory(with_vel=False)
    tr = load_measured([str(_write(tmp_path, cols))], "cube")[0]
    assert tr.vel_estimated and tr.omega_estimated
    # central differences are exact for the parabola inside; the body rate of a constant rotation is constant
    assert np.allclose(tr.vel[1:-1, 2], 1.0 - 9.81 * tr.t[1:-1], atol=1e-9)
    assert np.allclose(tr.omega[2:-2], omega, atol=2e-3)
    assert np.allclose(body_rates_from_quat(tr.t, tr.quat)[5], omega, atol=2e-3)


@pytest.mark.parametrize(
    "mutate, pattern",
    [
        (lambda c: c.pop("qz"), r"traj\.csv: missing column\(s\) qz"),
        (lambda c: c["t"].__setitem__(5, c["t"][4]), r"traj\.csv: column t is not strictly increasing"),
        (lambda c: c["vx"].__setitem__(7, np.nan), r"traj\.csv: column vx has NaN"),
        (lambda c: c["qw"].__imul__(1.3), r"traj\.csv: columns qw,qx,qy,qz are not a unit quaternion"),
        (lambda c: c["z"].__imul__(1e4), r"traj\.csv: column z reaches .* check the unit"),
        (lambda c: c.pop("wy"), r"traj\.csv: column\(s\) wy missing"),
        (lambda c: c["t"].__imul__(1000.0), r"traj\.csv: column t has a median step of 10 s"),
    ],
)
def test_bad_input_names_file_and_column(tmp_path, mutate, pattern):
    cols, _ = _rotation_trajectory()
    cols = {k: np.array(v, dtype=float) for k, v in cols.items()}
    mutate(cols)
    p = _write(tmp_path, cols)
    with pytest.raises(RispError, match=pattern):
        load_measured([str(p)], "cube")


@pytest.mark.parametrize("with_vel", [True, False], ids=["velocities-in-m/s", "no-velocities"])
def test_positions_in_millimetres_are_caught_by_their_speed(tmp_path, with_vel):
    """Millimetre positions stay inside the ±1000 bound but move at a thousandfold speed; the velocity columns,
    when given, are in m/s and looked fine, so the positions' own speed is checked (it used to run diagnose
    with every parameter at its bound, exit 0)."""
    cols, _ = _rotation_trajectory(with_vel=with_vel)
    for c in ("x", "y", "z"):
        cols[c] = np.asarray(cols[c]) * 1000.0
    with pytest.raises(RispError, match=r"traj\.csv: the positions change at .* m/s .*implausible in metres"):
        load_measured([str(_write(tmp_path, cols))], "cube")
    cols, _ = _rotation_trajectory(with_vel=with_vel)  # the same in metres reads
    assert load_measured([str(_write(tmp_path, cols, name="m.csv"))], "cube")[0].pos.shape == (40, 3)


def test_sidecar_problems(tmp_path):
    cols, _ = _rotation_trajectory()
    p = _write(tmp_path, cols, sidecar=None)
    with pytest.raises(RispError, match=r"no sidecar .*--side and --mass"):
        load_measured([str(p)], "cube")
    (tmp_path / "traj.json").write_text("{not json")
    with pytest.raises(RispError, match=r"traj\.json: sidecar is not valid JSON"):
        load_measured([str(p)], "cube")
    (tmp_path / "traj.json").write_text(json.dumps({"env": "quadrotor", "mass": 1.0}))
    with pytest.raises(RispError, match=r"sidecar says env 'quadrotor' but --env is 'cube'"):
        load_measured([str(p)], "cube")
    (tmp_path / "traj.json").write_text(json.dumps({"env": "cube", "side": 0.1}))
    with pytest.raises(RispError, match=r"lacks 'mass'"):
        load_measured([str(p)], "cube")


def test_truncated_file(tmp_path):
    src = CUBE_TOSSES / "toss_001.csv"
    text = src.read_text()
    p = tmp_path / "toss_001.csv"
    p.write_text(text[: len(text) // 2].rsplit(",", 3)[0])  # cut in the middle of a row
    with pytest.raises(RispError, match=r"toss_001\.csv: line \d+ has \d+ fields"):
        load_measured([str(p)], "cube", overrides={"side": 0.1048, "mass": 0.37})


def test_quadrotor_thrust_units(tmp_path):
    cols, _ = _rotation_trajectory()
    n = len(cols["t"])
    for i in range(4):
        cols[f"f{i}"] = np.full(n, 7357.5)  # grams-force mistaken for newtons
    sidecar = {"env": "quadrotor", "mass": 3.0, "arm_length": 0.3, "rotor_layout": "+", "gravity": 9.81,
               "angular_velocity_frame": "body"}
    p = _write(tmp_path, cols, sidecar=sidecar)
    with pytest.raises(RispError, match=r"column f0 reaches 7357.5 N.*newtons"):
        load_measured([str(p)], "quadrotor")
    cols.pop("f3")
    p = _write(tmp_path, cols, sidecar=sidecar)
    with pytest.raises(RispError, match=r"missing column\(s\) f3"):
        load_measured([str(p)], "quadrotor")


def test_cli_reports_one_line_error(tmp_path):
    from risp_tasks.cli import cli

    folder = tmp_path / "tosses"
    folder.mkdir()
    shutil.copy(CUBE_TOSSES / "toss_000.csv", folder / "toss_000.csv")
    (folder / "sidecar.json").write_text(json.dumps({"env": "cube", "side": 104.8, "mass": 0.37}))
    res = CliRunner().invoke(cli, ["diagnose", str(folder), "--env", "cube", "--out", str(tmp_path / "out"), "--quiet"])
    assert res.exit_code != 0
    lines = [ln for ln in res.output.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: ") and "'side' = 104.8" in lines[0]
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------------------------
# conventions of real logs declared in the sidecar (issue 12) and hostile files (issue 13)
# ------------------------------------------------------------------------------------------------
QUAD = {"env": "quadrotor", "mass": 3.0, "angular_velocity_frame": "body"}


def _quad_cols(n=40):
    cols, omega = _rotation_trajectory(n)
    for i in range(4):
        cols[f"f{i}"] = np.full(n, 7.4)
    return cols, omega


def _reorder(cols, names):
    return {k: cols[k] for k in names}


def test_quaternion_order_scalar_last_and_numbered(tmp_path):
    cols, _ = _quad_cols()
    ref = load_measured([str(_write(tmp_path, cols, QUAD, "ref.csv"))], "quadrotor")[0].quat
    last = _reorder(cols, [k for k in cols if k != "qw"] + ["qw"])  # header ...,qx,qy,qz,qw read by name
    assert list(last).index("qw") > list(last).index("qz")
    got = load_measured([str(_write(tmp_path, last, {**QUAD, "quaternion_order": "xyzw"}, "last.csv"))], "quadrotor")[0]
    assert np.allclose(got.quat, ref)
    with pytest.raises(RispError, match=r"header lists qx,qy,qz,qw but the sidecar says quaternion_order 'wxyz'"):
        load_measured([str(_write(tmp_path, last, {**QUAD, "quaternion_order": "wxyz"}, "clash.csv"))], "quadrotor")
    numbered = {("q" + str((["qx", "qy", "qz", "qw"].index(k)))) if k in ("qx", "qy", "qz", "qw") else k: v
                for k, v in last.items()}  # q0..q3 = x, y, z, w
    with pytest.raises(RispError, match=r"columns q0\.\.q3 without a sidecar 'quaternion_order'.*refusing to guess"):
        load_measured([str(_write(tmp_path, numbered, QUAD, "num.csv"))], "quadrotor")
    got = load_measured([str(_write(tmp_path, numbered, {**QUAD, "quaternion_order": "xyzw"}, "num2.csv"))], "quadrotor")[0]
    assert np.allclose(got.quat, ref)


def test_angular_velocity_frame(tmp_path):
    cols, omega_body = _quad_cols()
    bare = {k: v for k, v in QUAD.items() if k != "angular_velocity_frame"}
    with pytest.raises(RispError, match=r"has columns wx,wy,wz but the sidecar does not say their frame"):
        load_measured([str(_write(tmp_path, cols, bare, "a.csv"))], "quadrotor")
    # a rotation about a fixed axis has equal body and world rates; use a world-frame vector that is not
    tr = load_measured([str(_write(tmp_path, cols, QUAD, "b.csv"))], "quadrotor")[0]
    from risp_tasks.measured import quat_to_matrix_np

    R = quat_to_matrix_np(tr.quat)
    w_body = np.tile([0.3, -1.0, 2.0], (len(tr.t), 1))
    w_world = np.einsum("nij,nj->ni", R, w_body)
    cols.update(wx=w_world[:, 0], wy=w_world[:, 1], wz=w_world[:, 2])
    got = load_measured([str(_write(tmp_path, cols, {**QUAD, "angular_velocity_frame": "world"}, "c.csv"))], "quadrotor")[0]
    assert np.allclose(got.omega, w_body, atol=1e-9)


def test_pwm_actuator_delay_and_layout_keys(tmp_path):
    cols, _ = _quad_cols()
    n = len(cols["t"])
    for i in range(4):
        cols.pop(f"f{i}")
        cols[f"pwm{i}"] = 1000 + 500 * np.linspace(0.2, 0.8, n)
    side = {**QUAD, "actuator": "pwm", "pwm_range": [1000, 1500], "rotor_layout": "x", "arm_length": 0.16}
    with pytest.raises(RispError, match=r"'hover_throttle' is required with actuator 'pwm'"):
        load_measured([str(_write(tmp_path, cols, side, "p.csv"))], "quadrotor")
    side["hover_throttle"] = 0.5
    tr = load_measured([str(_write(tmp_path, cols, side, "p.csv"))], "quadrotor")[0]
    assert tr.thrust is None and np.allclose(tr.command[:, 0], np.linspace(0.2, 0.8, n))
    dt = tr.dt
    tr2 = load_measured([str(_write(tmp_path, cols, {**side, "actuator_delay": 2 * dt}, "d.csv"))], "quadrotor")[0]
    assert np.allclose(tr2.command[5:, 0], tr.command[3:-2, 0]) and tr2.command[0, 0] == tr.command[0, 0]
    cols["pwm2"][7] = 2000  # beyond pwm_range
    with pytest.raises(RispError, match=r"column pwm2 at data row 8 is outside the normalised range"):
        load_measured([str(_write(tmp_path, cols, side, "q.csv"))], "quadrotor")
    with pytest.raises(RispError, match=r"'rotor_layout' = 'H'; choose one of \+, x"):
        load_measured([str(_write(tmp_path, cols, {**side, "rotor_layout": "H"}, "r.csv"))], "quadrotor")


def test_negative_out_of_range_value_keeps_its_sign(tmp_path):
    cols, _ = _rotation_trajectory()
    cols["z"] = np.full(len(cols["t"]), -1021.49)
    with pytest.raises(RispError, match=r"column z reaches -1021\.49 at data row 1"):
        load_measured([str(_write(tmp_path, cols))], "cube")


def test_bom_binary_and_non_utf8_files(tmp_path):
    cols, _ = _rotation_trajectory()
    p = _write(tmp_path, cols)
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + p.read_bytes())
    (tmp_path / "bom.json").write_text(json.dumps(CUBE_SIDECAR))
    assert np.allclose(load_measured([str(bom)], "cube")[0].t, cols["t"] - cols["t"][0])
    binary = tmp_path / "bin.csv"
    binary.write_bytes(bytes(range(256)) * 40)
    (tmp_path / "bin.json").write_text(json.dumps(CUBE_SIDECAR))
    with pytest.raises(RispError, match=r"bin\.csv: not a (UTF-8 text|text|readable) CSV"):
        load_measured([str(binary)], "cube")
    latin = tmp_path / "latin.csv"
    latin.write_bytes(p.read_bytes().replace(b"t,x", "t\xb5,x".encode("latin-1"), 1))
    (tmp_path / "latin.json").write_text(json.dumps(CUBE_SIDECAR))
    with pytest.raises(RispError, match=r"latin\.csv: not a UTF-8 text CSV"):
        load_measured([str(latin)], "cube")


def test_large_file_read_in_chunks_equals_row_by_row(tmp_path, monkeypatch):
    import risp_tasks.measured as measured

    cols, _ = _rotation_trajectory(n=1003)
    p = _write(tmp_path, cols)
    monkeypatch.setattr(measured, "CHUNK_ROWS", 100)
    fast = measured.read_csv_columns(p)
    with open(p, newline="", encoding="utf-8-sig") as fh:
        header = measured._read_header(fh, p)
        slow = measured._validated_rows(__import__("csv").reader(fh), header, p, frozenset(header))
    assert all(np.array_equal(fast[h], slow[:, j]) for j, h in enumerate(header))
    assert len(fast["t"]) == 1003


@pytest.mark.parametrize("sidecar, message", [
    ({"env": "cube", "side": [0.1048], "mass": 0.37}, "sidecar key 'side' must be a number, got [0.1048]"),
    ({"env": "quadrotor", "mass": [3.0]}, "sidecar key 'mass' must be a number, got [3.0]"),
    ({"env": "quadrotor", "mass": 3.0, "inertia": 0.5}, "sidecar key 'inertia' must be a list of 3 numbers, got 0.5"),
    ({"env": "quadrotor", "mass": 3.0, "inertia": [0.5, 0.5]}, "'inertia' must be a list of 3 numbers, got [0.5, 0.5]"),
])
def test_sidecar_values_of_the_wrong_shape_are_one_line(tmp_path, sidecar, message):
    """A list where a number belongs was a TypeError traceback (or, for the inertia, silently the default)."""
    cols, _ = _quad_cols() if sidecar["env"] == "quadrotor" else _rotation_trajectory()
    p = _write(tmp_path, cols, sidecar=sidecar)
    with pytest.raises(RispError, match=re.escape(message)):
        load_measured([str(p)], sidecar["env"])


def test_files_whose_sidecars_disagree_are_refused(tmp_path):
    """One model is fitted to every file: a file with mass 1.5 among files with 3.0 was simulated with the first's."""
    cols, _ = _quad_cols()
    _write(tmp_path, cols, sidecar={"env": "quadrotor", "mass": 3.0, "angular_velocity_frame": "body", "estimated_by": {"video": "a"}}, name="a.csv")
    _write(tmp_path, cols, sidecar={"env": "quadrotor", "mass": 3.0, "angular_velocity_frame": "body", "estimated_by": {"video": "b"}}, name="b.csv")
    assert len(load_measured([str(tmp_path)], "quadrotor")) == 2  # per-file provenance may differ
    _write(tmp_path, cols, sidecar={"env": "quadrotor", "mass": 1.5, "angular_velocity_frame": "body"}, name="c.csv")
    with pytest.raises(RispError, match=r"a\.json and .*c\.json disagree on sidecar key 'mass' \(3\.0 vs 1\.5\)"):
        load_measured([str(tmp_path)], "quadrotor")


def test_sidecar_with_a_bom_and_upper_case_csv_names(tmp_path):
    cols, _ = _rotation_trajectory()
    p = _write(tmp_path, cols, name="RUN1.CSV")
    side = p.with_suffix(".json")
    side.write_text("\ufeff" + side.read_text(), encoding="utf-8")
    trajs = load_measured([str(tmp_path)], "cube")
    assert len(trajs) == 1 and trajs[0].sidecar.get("mass") == 0.37


def test_columns_no_reader_uses_do_not_block_reading(tmp_path):
    """A log's text column (PX4's flight mode), a NaN in a column diagnose never reads, or a trailing comma's unnamed
    column stopped the reading; they are left out.  A non-number in a column that is read is still an error."""
    cols, _ = _rotation_trajectory()
    p = _write(tmp_path, cols)
    lines = p.read_text().splitlines()
    modes = ["POSCTL" if i % 2 else "ALTCTL" for i in range(len(lines) - 1)]
    battery = ["15.2" if i != 5 else "nan" for i in range(len(lines) - 1)]
    p.write_text("\n".join([lines[0] + ",mode,battery_V,"] +
                           [f"{ln},{m},{b}," for ln, m, b in zip(lines[1:], modes, battery)]) + "\n")
    tr = load_measured([str(p)], "cube")[0]
    assert set(tr.extra) == set() and tr.n == len(lines) - 1
    assert np.allclose(tr.pos[:, 0], cols["x"])
    rows = p.read_text().splitlines()
    fields = rows[3].split(",")
    fields[1] = "oops"  # a read column (x) with text
    rows[3] = ",".join(fields)
    p.write_text("\n".join(rows) + "\n")
    with pytest.raises(RispError, match=r"data row 3 \(line 4\), column x: not a number \('oops'\)"):
        load_measured([str(p)], "cube")
    # a NaN is named by the same data-row count (it said 'data row' here and 'line' there, one apart)
    fields[1] = "nan"
    rows[3] = ",".join(fields)
    p.write_text("\n".join(rows) + "\n")
    with pytest.raises(RispError, match=r"column x has NaN/inf at data row 3 \(the first row after the header"):
        load_measured([str(p)], "cube")


def test_angular_velocity_in_degrees_per_second_is_caught(tmp_path):
    """Rates in deg/s stay under the 300 rad/s range check and turned a clean log `unexplained`; they are compared
    with the quaternion's own rates."""
    cols, _ = _rotation_trajectory()
    assert len(load_measured([str(_write(tmp_path, cols))], "cube")) == 1
    for w in ("wx", "wy", "wz"):
        cols[w] = np.degrees(cols[w])
    with pytest.raises(RispError, match=r"columns wx,wy,wz are typically 57\.3× the rates .*\(degrees per second\?\)"):
        load_measured([str(_write(tmp_path, cols))], "cube")


def test_a_hovering_bodys_gyro_is_not_taken_for_degrees(tmp_path):
    """A noisy quaternion's differences overstate a hovering body's rates far above its gyro's: only rates too
    large (deg/s) are refused, not too small."""
    n = 200
    rng = np.random.default_rng(0)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)) + np.c_[np.zeros(n), rng.normal(0, 1e-3, (n, 3))]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    cols = {"t": np.arange(n) * 0.01, "x": np.zeros(n), "y": np.zeros(n), "z": np.full(n, 1.0),
            "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3],
            "wx": rng.normal(0, 0.01, n), "wy": rng.normal(0, 0.01, n), "wz": rng.normal(0, 0.01, n)}
    for i in range(4):
        cols[f"f{i}"] = np.full(n, 7.4)
    p = _write(tmp_path, cols, sidecar={"env": "quadrotor", "mass": 3.0, "angular_velocity_frame": "body"})
    assert len(load_measured([str(p)], "quadrotor")) == 1


def test_columns_of_another_actuator_do_not_block_a_thrust_log(tmp_path):
    """known columns are the file's reader's: a thrust log's `throttle` (NaN) or `u0` (text) are not read."""
    cols, _ = _quad_cols()
    p = _write(tmp_path, cols, sidecar={"env": "quadrotor", "mass": 3.0, "angular_velocity_frame": "body"})
    lines = p.read_text().splitlines()
    p.write_text("\n".join([lines[0] + ",throttle,u0,,"] + [ln + ",nan,ARMED,," for ln in lines[1:]]) + "\n")
    tr = load_measured([str(p)], "quadrotor")[0]
    assert "throttle" not in tr.extra and "u0" not in tr.extra and tr.thrust.shape == (40, 4)


def test_sidecars_that_say_the_same_in_other_words_agree(tmp_path):
    cols, _ = _quad_cols()
    base = {"env": "quadrotor", "mass": 3.0, "angular_velocity_frame": "body"}
    _write(tmp_path, cols, sidecar={**base, "gravity": 9.81, "actuator": "Thrust"}, name="a.csv")
    _write(tmp_path, cols, sidecar=base, name="b.csv")  # gravity and actuator absent: their defaults
    assert len(load_measured([str(tmp_path)], "quadrotor")) == 2


def test_sampling_step_and_even_segments_with_rounded_timestamps():
    """A 400 Hz log with millisecond timestamps (steps of 2 and 3 ms) is sampled every 2.5 ms and its segments are
    even; a sample dropped every 25 leaves no 30-step stretch, and the rollout horizon is cut to the longest one."""
    from types import SimpleNamespace

    from risp_tasks.diagnose.fit import even_starts, longest_even
    from risp_tasks.measured import sampling_step

    t = np.round(np.arange(2000) * 2.5) / 1000
    assert set(np.round(np.diff(t) * 1000)) == {2.0, 3.0}
    assert sampling_step(t) == pytest.approx(0.0025) and even_starts(t, 30)[:-30].mean() > 0.95
    dropped = np.delete(np.arange(2000) * 0.01, np.arange(20, 2000, 25))
    assert sampling_step(dropped) == pytest.approx(0.01)
    assert longest_even([SimpleNamespace(t=dropped)], 60) == 23


def test_two_trailing_commas_are_not_duplicate_columns(tmp_path):
    cols, _ = _rotation_trajectory()
    p = _write(tmp_path, cols)
    lines = p.read_text().splitlines()
    p.write_text("\n".join([lines[0] + ",,"] + [ln + ",," for ln in lines[1:]]) + "\n")
    assert load_measured([str(p)], "cube")[0].n == len(lines) - 1


def _hand_state_columns():
    from risp_tasks.measured import generic_columns

    return ["t", *generic_columns("hand")[0]]


@pytest.mark.parametrize("env, cols, words", [
    ("rod", ["t"] + [f"z{i}" for i in range(10)], "a rod estimate is not a diagnose input"),
    ("hand", "states", "an estimate made without --actions"),
])
def test_an_estimate_file_diagnose_cannot_read_says_why(tmp_path, env, cols, words):
    """risp-task estimate's CSV (its sidecar names the network: estimated_by) lacking what diagnose fits: the
    missing-columns line says why (no --actions; the rod's sensor heights) instead of leaving the user to guess."""
    from risp_tasks.measured import read_trajectory

    cols = _hand_state_columns() if cols == "states" else cols
    path = tmp_path / "trajectory.csv"
    write_trajectory_csv(path, {c: np.linspace(0, 1, 5) + i for i, c in enumerate(cols)},
                         {"env": env, "estimated_by": {"model_sha256": "0" * 64}})
    with pytest.raises(RispError, match="missing column") as e:
        read_trajectory(path, env)
    assert words in str(e.value)
    # a measured file (no estimated_by) gets the plain line
    write_trajectory_csv(path, {c: np.linspace(0, 1, 5) + i for i, c in enumerate(cols)}, {"env": env})
    with pytest.raises(RispError, match="missing column") as e:
        read_trajectory(path, env)
    assert words not in str(e.value)


def test_an_estimate_missing_state_columns_gets_no_actions_hint(tmp_path):
    """The --actions hint only where the commands are all that is missing: a hand file without its states (or a
    cube file, which has no commands) keeps the plain missing-columns line."""
    from risp_tasks.measured import read_trajectory

    path = tmp_path / "trajectory.csv"
    write_trajectory_csv(path, {"t": np.linspace(0, 1, 5)}, {"env": "hand", "estimated_by": {"model_sha256": "0"}})
    with pytest.raises(RispError, match="missing column") as e:
        read_trajectory(path, "hand")
    assert "without --actions" not in str(e.value)


@pytest.mark.parametrize("mass, message", [
    ("9" * 400, "sidecar key 'mass' must be a finite number"),  # float() overflows: was an OverflowError traceback
    ("9" * 5000, "sidecar is not valid JSON"),  # beyond int's 4300-digit string limit: was a ValueError traceback
])
def test_sidecar_integers_beyond_float_are_one_line(tmp_path, mass, message):
    cols, _ = _quad_cols()
    p = _write(tmp_path, cols, sidecar={"env": "quadrotor", "mass": 3.0})
    p.with_suffix(".json").write_text('{"env": "quadrotor", "mass": %s}' % mass)
    with pytest.raises(RispError, match=re.escape(message)):
        load_measured([str(p)], "quadrotor")


@pytest.mark.parametrize("extra, message", [
    ({"k_f": -5}, "sidecar key 'k_f' = -5 must lie in [1e-09, inf]"),
    ({"k_f": float("nan")}, "sidecar key 'k_f' (a quadrotor simulator parameter) must be a finite number"),
    ({"Ixx": "big"}, "sidecar key 'Ixx' (a quadrotor simulator parameter) must be a finite number"),
    ({"rotor_spin": [True, -1, True, -1]}, "sidecar key 'rotor_spin' must be a list of 4 +1/-1 signs"),
])
def test_sidecar_keys_that_are_simulator_parameters_are_checked_naming_the_file(tmp_path, extra, message):
    """Such keys go to the simulator as they are: a negative k_f was refused by the simulator without naming the file,
    a NaN made two identical files 'disagree' (NaN ≠ NaN)."""
    cols, _ = _quad_cols()
    p = _write(tmp_path, cols, sidecar={"env": "quadrotor", "mass": 3.0, **extra})
    with pytest.raises(RispError, match=re.escape(message)) as info:
        load_measured([str(p)], "quadrotor")
    assert str(p.with_suffix(".json")) in str(info.value)


def test_a_trailing_blank_line_reads_without_numpy_warnings(tmp_path, recwarn):
    cols, _ = _quad_cols()
    p = _write(tmp_path, cols, sidecar={"env": "quadrotor", "mass": 3.0, "angular_velocity_frame": "body"})
    expected = load_measured([str(p)], "quadrotor")[0].pos
    with open(p, "a") as f:
        f.write("\n\n")
    assert np.array_equal(load_measured([str(p)], "quadrotor")[0].pos, expected)
    assert not [w for w in recwarn.list if "contained no data" in str(w.message)], [str(w.message) for w in recwarn.list]


def test_command_line_overrides_are_named_as_options():
    """--side inf was reported as the bundled sidecar.json's 'side' key, a value the file does not hold."""
    for side, words in ((float("inf"), "--side inf: must be a finite number"),
                        (104.8, "--side 104.8: outside the plausible range [0.005, 2] in SI units")):
        with pytest.raises(RispError, match=re.escape(words)):
            load_measured([str(CUBE_TOSSES)], "cube", limit=1, overrides={"side": side})
