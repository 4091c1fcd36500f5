"""Measured trajectories: CSV files with a header in SI units plus a JSON sidecar (docs/measured-data.md).

    >>> from risp_tasks.measured import load_measured
    >>> trajs = load_measured(["data/cube-tosses"], env="cube")

Every trajectory is validated on reading; anything a user can fix (missing column, non-increasing time,
NaN, a quaternion that is not unit length, a value in the wrong unit) raises :class:`RispError` with one
line naming the file and the column.  Velocities absent from the file are estimated by central
differences of the positions (linear, world frame) and of the quaternion (angular, body frame,
ω = 2·Im(q* ⊗ q̇)) and flagged as estimated.
"""

from __future__ import annotations

import csv
import json
import math
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from risp_data.errors import RispError
from risp_data.numbers import is_finite_number
from risp_data.atomic import atomic_write, write_text_atomic

POSE_COLUMNS = ("t", "x", "y", "z", "qw", "qx", "qy", "qz")
VEL_COLUMNS = ("vx", "vy", "vz")
OMEGA_COLUMNS = ("wx", "wy", "wz")
THRUST_COLUMNS = ("f0", "f1", "f2", "f3")

#: Constants of the real cube in data/cube-tosses (its README); used when that folder has no sidecar.
CONTACTNETS_CUBE = {"env": "cube", "side": 0.1048, "mass": 0.37, "gravity": 9.81}

# Plausible ranges of sidecar values in SI units: outside them the value is almost surely in another
# unit (a cube side of 104.8 "m" is millimetres), so reading stops with an error naming the key.
SIDECAR_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "cube": {"side": (0.005, 2.0), "mass": (0.001, 100.0), "gravity": (1.0, 30.0)},
    "quadrotor": {
        "mass": (0.01, 50.0),
        "arm_length": (0.02, 3.0),
        "inertia": (1e-6, 20.0),
        "yaw_torque_coefficient": (0.0, 1.0),
        "gravity": (1.0, 30.0),
        "hover_throttle": (0.01, 1.0),
        "actuator_delay": (0.0, 0.5),
    },
    "hand": {"gravity": (0.0, 30.0)},
    "rod": {"gravity": (0.0, 30.0)},
}
#: sidecar keys whose value is a list, and its length ([Ixx, Iyy, Izz]); every other key of SIDECAR_RANGES is a number
LIST_KEYS = {"inertia": 3}
REQUIRED_SIDECAR_KEYS = {"cube": ("side", "mass"), "quadrotor": ("mass",), "hand": (), "rod": ()}

#: Conventions of real logs, declared in the sidecar (docs/measured-data.md §Conventions): allowed values.
CHOICES = {
    "quaternion_order": ("wxyz", "xyzw"),
    "angular_velocity_frame": ("body", "world"),
    "rotor_layout": ("+", "x"),
    "actuator": ("thrust", "normalized", "pwm", "collective", "collective_normalized"),
    "thrust_map": ("linear", "quadratic"),
}
#: Actuator columns: per-rotor thrust [N], normalised command [0, 1], or PWM [µs] mapped to [0, 1] by pwm_range.
ACTUATOR_COLUMNS = {"thrust": THRUST_COLUMNS, "normalized": ("u0", "u1", "u2", "u3"),
                    "pwm": ("pwm0", "pwm1", "pwm2", "pwm3"),
                    # collective commands: diagnose's translational mode (attitude from the data)
                    "collective": ("thrust",), "collective_normalized": ("throttle",)}
NUMBERED_QUAT = ("q0", "q1", "q2", "q3")

MAX_ABS_POSITION = 1000.0  # m
MAX_SPEED = 100.0  # m/s
MAX_ANGULAR_SPEED = 300.0  # rad/s
QUAT_NORM_TOL = 1e-2  # | |q| - 1 | above this is not a unit quaternion (rounding in CSVs is ~1e-7)


@dataclass(frozen=True)
class Sidecar:
    """The JSON sidecar: environment name and nominal physical parameters (SI units)."""

    env: str
    values: dict
    source: str  # path of the JSON file, or a note saying where the values came from

    def get(self, key: str, default=None):
        return self.values.get(key, default)


@dataclass(frozen=True)
class Trajectory:
    """One measured trajectory, validated, SI units.

    ``extra`` holds further numeric columns keyed by name (for environments whose state is not a rigid
    body pose: hand, rod; columns named as the simulator's state names, actions ``u0…``).
    """

    name: str
    path: str
    t: np.ndarray  # (N,)
    pos: np.ndarray | None  # (N, 3) world frame (None: environment without a rigid-body pose)
    quat: np.ndarray | None  # (N, 4) scalar-first, body to world, unit, sign-continuous
    vel: np.ndarray | None  # (N, 3) world frame
    omega: np.ndarray | None  # (N, 3) body frame
    thrust: np.ndarray | None  # (N, 4) newtons (quadrotor, actuator "thrust") or None
    sidecar: Sidecar
    vel_estimated: bool = False
    omega_estimated: bool = False
    extra: dict = field(default_factory=dict)
    # (N, 4) normalised rotor commands in [0, 1] (actuator "normalized"/"pwm"), or (N, 1) a collective command
    # (actuator "collective" [N] / "collective_normalized" [0, 1])
    command: np.ndarray | None = None

    @property
    def n(self) -> int:
        return len(self.t)

    @property
    def dt(self) -> float:
        """Sampling interval [s] (:func:`sampling_step`)."""
        return sampling_step(self.t)

    def slice(self, start: int, stop: int, suffix: str) -> "Trajectory":
        """Samples [start, stop) as a new trajectory (time kept as measured)."""
        sl = slice(start, stop)
        return Trajectory(
            name=f"{self.name}{suffix}",
            path=self.path,
            t=self.t[sl],
            pos=None if self.pos is None else self.pos[sl],
            quat=None if self.quat is None else self.quat[sl],
            vel=None if self.vel is None else self.vel[sl],
            omega=None if self.omega is None else self.omega[sl],
            thrust=None if self.thrust is None else self.thrust[sl],
            command=None if self.command is None else self.command[sl],
            sidecar=self.sidecar,
            vel_estimated=self.vel_estimated,
            omega_estimated=self.omega_estimated,
            extra={k: v[sl] for k, v in self.extra.items()},
        )


# ------------------------------------------------------------------------------------------------
# file discovery and sidecars
# ------------------------------------------------------------------------------------------------
def expand_paths(paths: list[str] | tuple[str, ...]) -> list[Path]:
    """Files and folders -> sorted list of CSV files (folders contribute their ``*.csv``)."""
    if not paths:
        raise RispError("no measured data given: pass one or more CSV files or folders")
    files: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            found = sorted(f for f in p.iterdir() if f.suffix.lower() == ".csv" and f.is_file())  # RUN1.CSV too
            if not found:
                raise RispError(f"{p}: folder contains no .csv files")
            files += found
        elif p.is_file():
            if p.suffix.lower() != ".csv":
                raise RispError(f"{p}: expected a .csv file")
            files.append(p)
        else:
            raise RispError(f"{p}: no such file or folder")
    seen, unique = set(), []
    for f in files:
        if f.resolve() not in seen:
            seen.add(f.resolve())
            unique.append(f)
    return unique


def _is_contactnets_folder(folder: Path) -> bool:
    readme = folder / "README.md"
    try:
        return readme.is_file() and "ContactNets" in readme.read_text(errors="replace")[:4000]
    except OSError:
        return False


def sampling_step(t: np.ndarray, span: int = 10) -> float:
    """The sampling interval Δ [s]: the median over i of (t[i+m] − t[i]) / m, m = min(span, (N − 1) // 4) (at least
    1).  The median of single steps would take a 400 Hz log with millisecond timestamps (steps of 2 and 3 ms) for 2
    or 3 ms, not 2.5; spans of m steps average the rounding out, and dropped samples (in fewer than half the spans)
    do not move the median."""
    t = np.asarray(t, np.float64)
    single = float(np.median(np.diff(t)))
    m = max(1, min(span, (len(t) - 1) // 4))
    spans = float(np.median((t[m:] - t[:-m]) / m))
    # evenly sampled data (the usual case) keep the plain median step to the last bit: a stiff contact fit moved
    # with a 1e-17 s difference in the step
    return single if abs(spans - single) <= 1e-9 * single else spans


def find_sidecar(csv_path: Path, env: str, overrides: dict | None = None) -> Sidecar:
    """``foo.csv`` -> ``foo.json``, else ``sidecar.json`` in the same folder; see docs/measured-data.md.

    Without either, a cube folder recognised as the ContactNets tosses (its README) gets that cube's
    constants; otherwise the values must come from ``overrides`` (command-line ``--side/--mass``).
    Overrides always win over file values.
    """
    overrides = {k: v for k, v in (overrides or {}).items() if v is not None}
    for key, v in overrides.items():  # the command line's values are named as options, not blamed on a sidecar file
        lo, hi = SIDECAR_RANGES.get(env, {}).get(key, (-math.inf, math.inf))
        if not is_finite_number(v):
            raise RispError(f"--{key} {v!r}: must be a finite number")
        if not lo <= v <= hi:
            raise RispError(f"--{key} {v!r}: outside the plausible range [{lo:g}, {hi:g}] in SI units (check the unit)")
    for cand in (csv_path.with_suffix(".json"), csv_path.parent / "sidecar.json"):
        if cand.is_file():
            try:
                values = json.loads(cand.read_text(encoding="utf-8-sig"))  # a BOM, as the CSVs may carry
            except (OSError, ValueError) as e:  # ValueError: JSONDecodeError, or an integer of over 4300 digits
                raise RispError(f"{cand}: sidecar is not valid JSON ({e})") from None
            if not isinstance(values, dict):
                raise RispError(f"{cand}: sidecar must be a JSON object")
            source = str(cand)
            break
    else:
        if env == "cube" and _is_contactnets_folder(csv_path.parent):
            values, source = dict(CONTACTNETS_CUBE), "default: ContactNets cube constants (folder README)"
        elif env == "cube" and overrides:
            values, source = {"env": "cube"}, "command line"
        else:
            raise RispError(
                f"{csv_path}: no sidecar ({csv_path.with_suffix('.json').name} or sidecar.json) "
                f"naming the environment and its nominal parameters"
                + (" (or pass --side and --mass)" if env == "cube" else "")
            )
    values = {**values, **overrides}
    file_env = values.get("env", env)
    if file_env != env:
        raise RispError(f"{source}: sidecar says env {file_env!r} but --env is {env!r}")
    values["env"] = env
    _check_sidecar(values, env, source)
    return Sidecar(env=env, values=values, source=source)


def _check_sidecar(values: dict, env: str, source: str) -> None:
    for key in REQUIRED_SIDECAR_KEYS.get(env, ()):
        if key not in values:
            raise RispError(f"{source}: sidecar lacks {key!r} (required for {env})")
    for key, allowed in CHOICES.items():
        if key in values and str(values[key]).lower() not in allowed:
            raise RispError(f"{source}: sidecar key {key!r} = {values[key]!r}; choose one of {', '.join(allowed)}")
    for key, check in (("rotor_angles_deg", is_finite_number),
                       ("rotor_spin", lambda v: not isinstance(v, bool) and v in (1, -1))):
        if key in values and not (isinstance(values[key], list) and len(values[key]) == 4 and all(map(check, values[key]))):
            raise RispError(f"{source}: sidecar key {key!r} must be a list of 4 {'numbers' if key.endswith('deg') else '+1/-1 signs'}, "
                            f"got {values[key]!r}")
    noise = values.get("measurement_noise")
    if noise is not None and not (isinstance(noise, dict) and noise and all(
            is_finite_number(v) and v > 0 for v in noise.values())):
        raise RispError(f"{source}: sidecar key 'measurement_noise' must map channel groups (position, attitude, velocity, "
                        f"angular velocity; hand/rod: coordinate, rate) to positive standard deviations in SI units, got {noise!r}")
    phi = values.get("measurement_noise_correlation", 0.0)
    if not (is_finite_number(phi) and 0.0 <= phi < 1.0):
        raise RispError(f"{source}: sidecar key 'measurement_noise_correlation' must lie in [0, 1), got {phi!r}")
    actuator = str(values.get("actuator", "thrust")).lower()
    if str(values.get("thrust_map", "linear")).lower() == "quadratic" and actuator not in ("normalized", "pwm"):
        raise RispError(f"{source}: sidecar key 'thrust_map' = 'quadratic' needs per-rotor normalised commands "
                        f"(actuator 'normalized' or 'pwm'), not {actuator!r}")
    if actuator in ("normalized", "pwm", "collective_normalized") and "hover_throttle" not in values:
        raise RispError(f"{source}: sidecar key 'hover_throttle' is required with actuator {actuator!r} (the normalised "
                        f"command that holds hover, e.g. PX4's MPC_THR_HOVER; it starts the fitted thrust map)")
    if actuator == "pwm":
        lo_hi = values.get("pwm_range", [1000, 2000])
        if not (isinstance(lo_hi, list) and len(lo_hi) == 2 and all(isinstance(v, (int, float)) for v in lo_hi)
                and lo_hi[1] > lo_hi[0]):
            raise RispError(f"{source}: sidecar key 'pwm_range' must be [min, max] with max > min, got {lo_hi!r}")
    for key, (lo, hi) in SIDECAR_RANGES.get(env, {}).items():
        if key not in values:
            continue
        raw = values[key]
        if key in LIST_KEYS:  # the one list-valued key: the principal inertia
            if not (isinstance(raw, list) and len(raw) == LIST_KEYS[key]):
                raise RispError(f"{source}: sidecar key {key!r} must be a list of {LIST_KEYS[key]} numbers, got {raw!r}")
        elif isinstance(raw, (list, tuple, dict)):
            raise RispError(f"{source}: sidecar key {key!r} must be a number, got {raw!r}")
        vals = raw if isinstance(raw, list) else [raw]
        for v in vals:
            if not is_finite_number(v):
                raise RispError(f"{source}: sidecar key {key!r} must be a finite number, got {str(raw)[:40]}")
            if not lo <= v <= hi:
                raise RispError(
                    f"{source}: sidecar key {key!r} = {v} is outside the plausible range [{lo}, {hi}] "
                    f"in SI units (check the unit)"
                )
    # keys that are simulator parameter names (k_f, Ixx, log10_kn, …) go to the simulator as they are: checked here,
    # naming the file, rather than by the simulator's own input check (or a NaN's disagreement with itself)
    from risp_tasks.sims import get_simulator

    sim = get_simulator(env)
    for key, (lo, hi) in zip(sim.param_names, sim.param_bounds):
        if key not in values or key in SIDECAR_RANGES.get(env, {}):
            continue
        v = values[key]
        if not is_finite_number(v):
            raise RispError(f"{source}: sidecar key {key!r} (a {env} simulator parameter) must be a finite number, "
                            f"got {str(v)[:40]}")
        if not lo <= v <= hi:
            raise RispError(f"{source}: sidecar key {key!r} = {v:g} must lie in [{lo:g}, {hi:g}] (the simulator's "
                            f"physical bounds)")


# ------------------------------------------------------------------------------------------------
# CSV reading and validation
# ------------------------------------------------------------------------------------------------
#: Files larger than this are read in chunks with a progress bar.
CHUNK_ROWS = 200_000


def read_csv_columns(path: Path, known: frozenset[str] = frozenset(), progress: bool = False) -> dict[str, np.ndarray]:
    """Header + numeric rows -> {column: float64 array}. Errors name the file, row and column.

    Fast path: numpy's C parser in chunks of CHUNK_ROWS rows straight into float64 (a 200 MB log without
    Python objects per cell); any irregularity re-reads the file with the row-by-row validator, whose
    message names the line and column.  A UTF-8 byte-order mark is skipped; binary or non-UTF-8 content
    is one clear error.
    """
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            header = _read_header(fh, path)
            try:
                data = _fast_rows(fh, len(header), path, progress)
            except (ValueError, UnicodeDecodeError, csv.Error):
                data = None
        if data is None:
            with open(path, newline="", encoding="utf-8-sig") as fh:
                _read_header(fh, path)
                data = _validated_rows(csv.reader(fh), header, path, known)
    except UnicodeDecodeError as e:
        raise RispError(f"{path}: not a UTF-8 text CSV (byte {e.object[e.start:e.start + 1]!r} at offset {e.start}); "
                        f"is it a binary file?") from None
    except csv.Error as e:
        raise RispError(f"{path}: not a readable CSV ({e}); is it a binary file?") from None
    except OSError as e:
        raise RispError(f"{path}: cannot read ({e.strerror})") from None
    if len(data) < 3:
        raise RispError(f"{path}: needs at least 3 rows of data, found {len(data)}")
    # a column the reader does not use is kept only where it is all numbers (an unnamed one never)
    return {h: np.ascontiguousarray(data[:, j]) for j, h in enumerate(header)
            if h in known or (h and np.isfinite(data[:, j]).all())}


def _read_header(fh, path: Path) -> list[str]:
    line = fh.readline()
    if not line:
        raise RispError(f"{path}: empty file (expected a header row)")
    if "\x00" in line:
        raise RispError(f"{path}: not a text CSV (NUL bytes in the header); is it a binary file?")
    header = [h.strip() for h in next(csv.reader([line]))]
    named = [h for h in header if h]  # unnamed columns (trailing commas) are left out later, however many
    if len(set(named)) != len(named):
        dup = sorted({h for h in named if named.count(h) > 1})
        raise RispError(f"{path}: duplicate column(s) {', '.join(dup)}")
    return header


def _fast_rows(fh, ncols: int, path: Path, progress: bool) -> np.ndarray:
    """All data rows by numpy's parser, chunk by chunk (ValueError on anything irregular)."""
    from tqdm.auto import tqdm

    size = os.path.getsize(path)
    chunks = []
    with tqdm(unit=" rows", unit_scale=True, desc=f"reading {path.name} ({size / 1e6:.0f} MB)", leave=False,
              disable=not progress or size < 20_000_000) as bar:
        while True:
            with warnings.catch_warnings():  # a trailing blank line: numpy warns, the rows are read all the same
                warnings.filterwarnings("ignore", message=".*contained no data")
                block = np.loadtxt(fh, delimiter=",", dtype=np.float64, ndmin=2, max_rows=CHUNK_ROWS, comments=None)
            if block.size == 0:
                break
            if block.shape[1] != ncols:
                raise ValueError("column count")
            chunks.append(block)
            bar.update(len(block))
            if len(block) < CHUNK_ROWS:
                break
    return np.concatenate(chunks) if chunks else np.zeros((0, ncols))


def columns_read(env: str, sidecar: Sidecar) -> frozenset[str]:
    """The columns the reader of ``env`` uses for a file with this sidecar (its actuator's); the others may hold
    anything (read_csv_columns leaves out those that are not all numbers)."""
    if env in ("hand", "rod"):
        states, actions = generic_columns(env)
        return frozenset(("t",) + states + actions)
    actuator = str(sidecar.get("actuator", "thrust")).lower() if env == "quadrotor" else None
    return frozenset(POSE_COLUMNS + NUMBERED_QUAT + VEL_COLUMNS + OMEGA_COLUMNS
                     + (ACTUATOR_COLUMNS.get(actuator, ()) if actuator else ()))


def _validated_rows(reader, header: list[str], path: Path, known: frozenset[str]) -> np.ndarray:
    """Row by row; a non-number in a column not in ``known`` (a log's flight-mode text, a trailing comma's empty
    column) makes that column NaN (read_csv_columns then leaves it out), elsewhere it is an error naming the cell."""
    rows = []  # errors name the data row (as _check_finite does) and the file's line (the header is line 1)
    for i, row in enumerate(reader, start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise RispError(f"{path}: line {i} has {len(row)} fields, header has {len(header)} (truncated file?)")
        vals = []
        for col, c in zip(header, row):
            try:
                vals.append(float(c))
            except ValueError:
                if col in known:
                    raise RispError(f"{path}: data row {len(rows) + 1} (line {i}), column {col}: not a number "
                                    f"({c!r})") from None
                vals.append(float("nan"))
        rows.append(vals)
    return np.asarray(rows, dtype=np.float64).reshape(-1, len(header))


class MissingColumns(RispError):
    """A required column is absent; ``missing`` names them (for a caller that explains why, e.g. an estimate)."""

    def __init__(self, path: Path, missing: list[str]):
        super().__init__(f"{path}: missing column(s) {', '.join(missing)}")
        self.missing = tuple(missing)


def _require(cols: dict, names: tuple[str, ...], path: Path) -> None:
    missing = [c for c in names if c not in cols]
    if missing:
        raise MissingColumns(path, missing)


def _check_finite(cols: dict, path: Path) -> None:
    for name, v in cols.items():
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise RispError(f"{path}: column {name} has NaN/inf at data row {bad[0] + 1} (the first row after the "
                            "header is data row 1)")


def _check_time(t: np.ndarray, path: Path) -> None:
    d = np.diff(t)
    bad = np.flatnonzero(d <= 0)
    if bad.size:
        raise RispError(f"{path}: column t is not strictly increasing (data row {bad[0] + 2}: {t[bad[0] + 1]} after {t[bad[0]]})")
    dt = float(np.median(d))
    if not 1e-5 <= dt <= 1.0:
        raise RispError(f"{path}: column t has a median step of {dt:g} s; expected seconds (1e-5 … 1 s)")
    if d.max() > 5 * dt:
        i = int(np.argmax(d))
        raise RispError(f"{path}: column t has a gap of {d[i]:g} s at data row {i + 2} (median step {dt:g} s); split the file there")


def _check_quat(q: np.ndarray, path: Path, names=("qw", "qx", "qy", "qz")) -> np.ndarray:
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUAT_NORM_TOL)
    if bad.size:
        raise RispError(
            f"{path}: columns {','.join(names)} are not a unit quaternion at data row {bad[0] + 1} (|q| = {norm[bad[0]]:.4g})"
        )
    q = q / norm[:, None]
    # q and -q are the same rotation: make the sequence continuous so differences are meaningful
    for i in range(1, len(q)):
        if np.dot(q[i], q[i - 1]) < 0:
            q[i] = -q[i]
    return q


def _check_range(cols: dict, names: tuple[str, ...], limit: float, unit: str, path: Path) -> None:
    for name in names:
        if name in cols:
            i = int(np.argmax(np.abs(cols[name])))
            v = float(cols[name][i])  # signed: "z reaches -1021.49", not 1021.49
            if abs(v) > limit:
                raise RispError(f"{path}: column {name} reaches {v:g} at data row {i + 1}, implausible in {unit} "
                                f"(|{name}| ≤ {limit:g}); check the unit and the data")


def _check_position_speed(dpos: np.ndarray, path: Path) -> None:
    """The speed the positions themselves imply (``dpos`` = dp/dt), whether or not velocity columns are given:
    positions in millimetres (a thousandfold speed) are caught here even when the given velocities are in m/s."""
    speed = np.abs(dpos)
    row, axis = np.unravel_index(int(np.argmax(speed)), speed.shape)
    if speed[row, axis] > MAX_SPEED:
        name = "xyz"[axis]
        raise RispError(f"{path}: the positions change at {speed[row, axis]:.4g} m/s ({name} near data row {row + 1}), "
                        f"implausible in metres (≤ {MAX_SPEED:g} m/s): check the unit (millimetres?) and the time column")


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of scalar-first quaternions (..., 4)."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def body_rates_from_quat(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """ω_body = 2 · Im(q* ⊗ q̇) with q̇ by central differences (q̇ = ½ q ⊗ (0, ω))."""
    qdot = np.gradient(q, t, axis=0)
    conj = q * np.array([1.0, -1.0, -1.0, -1.0])
    return 2.0 * quat_mul(conj, qdot)[:, 1:]


def _check_consistency(env: str, cols: dict, side: Sidecar, path: Path) -> None:
    if env == "cube":
        s = float(side.get("side"))
        zmin = float(np.min(cols["z"]))
        if zmin < -s:
            raise RispError(f"{path}: column z goes to {zmin:g} m, more than a side ({s} m) below the floor z = 0; check the unit")
    if env == "quadrotor" and str(side.get("actuator", "thrust")).lower() == "thrust":
        mg = float(side.get("mass")) * float(side.get("gravity", 9.81))
        for name in THRUST_COLUMNS:
            m = float(np.max(np.abs(cols[name])))
            if m > 20 * mg:
                raise RispError(
                    f"{path}: column {name} reaches {m:g} N, more than 20× the weight ({mg:.3g} N); thrusts must be in newtons"
                )


#: given angular rates whose typical size is more than this factor above the quaternion's own rates are in another
#: unit (deg/s is 57.3×); only checked where the quaternion's rates exceed RATE_CHECK_MIN rad/s
RATE_UNIT_FACTOR, RATE_CHECK_MIN = 5.0, 0.05


def _check_rate_unit(omega: np.ndarray, from_quat: np.ndarray, path: Path) -> None:
    """wx, wy, wz against the rates the quaternion column implies: degrees per second (or rpm) pass every range
    check below 300 "rad/s" and turned a clean log `unexplained`."""
    given, implied = np.median(np.linalg.norm(omega, axis=1)), np.median(np.linalg.norm(from_quat, axis=1))
    if implied < RATE_CHECK_MIN:
        return
    # only rates too large are flagged (deg/s, rpm): differences of a noisy quaternion inflate the implied rates of a
    # hovering or resting body far above a gyro's, so a small ratio says nothing about the unit
    ratio = given / implied
    if ratio > RATE_UNIT_FACTOR:
        raise RispError(f"{path}: columns wx,wy,wz are typically {ratio:.3g}× the rates of the quaternion columns "
                        f"({given:.3g} against {implied:.3g} rad/s); angular velocity must be in rad/s"
                        + (" (degrees per second?)" if 30 < ratio < 100 else ""))


def generic_columns(env: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(state columns, action columns) of an environment without a rigid-body pose (hand, rod):
    the simulator's state names and ``u0 … u{A-1}``."""
    import importlib

    spec = importlib.import_module(f"risp_tasks.sims.{env}").SPEC
    return tuple(spec.state_names), tuple(f"u{i}" for i in range(spec.action_dim))


def _read_generic(path: Path, env: str, sidecar: Sidecar, cols: dict, known: frozenset[str]) -> Trajectory:
    states, actions = generic_columns(env)
    _require(cols, ("t",) + states + actions, path)
    _check_finite({k: cols[k] for k in known}, path)
    t = cols["t"]
    _check_time(t, path)
    return Trajectory(name=path.stem, path=str(path), t=t - t[0], pos=None, quat=None, vel=None, omega=None,
                      thrust=None, sidecar=sidecar, extra={k: v for k, v in cols.items() if k != "t"})


def read_trajectory(path: Path, env: str, overrides: dict | None = None) -> Trajectory:
    """Read and validate one CSV (+ sidecar) for environment ``env``."""
    sidecar = find_sidecar(path, env, overrides)
    known = columns_read(env, sidecar)
    cols = read_csv_columns(path, known)
    try:
        return _read_columns(path, env, sidecar, cols, known)
    except MissingColumns as e:
        hint = _estimate_hint(env, sidecar, e.missing)
        if hint:
            raise RispError(f"{e}: {hint}") from None
        raise


def _estimate_hint(env: str, sidecar: Sidecar, missing: tuple[str, ...]) -> str | None:
    """Why a ``risp-task estimate`` file (its sidecar has ``estimated_by``) lacks columns, and what to do: the rod's
    estimate is not a diagnose input; a quadrotor or hand estimate whose only missing columns are the commands was
    made without --actions.  None for anything else (the plain missing-columns line stands)."""
    if sidecar.get("estimated_by") is None:
        return None
    if env == "rod":
        return ("risp-task estimate writes the rod's ten sensor heights (z0…z9), not the node positions and "
                "loads that diagnose fits: a rod estimate is not a diagnose input")
    commands = set(ACTUATOR_COLUMNS["thrust"]) if env == "quadrotor" else \
        set(generic_columns(env)[1]) if env == "hand" else set()
    if missing and set(missing) <= commands:
        return ("an estimate made without --actions; make it again with --actions A.csv (the commands, which "
                "diagnose needs beside the states)")
    return None


def _read_columns(path: Path, env: str, sidecar: Sidecar, cols: dict, known: frozenset[str]) -> Trajectory:
    if env in ("hand", "rod"):
        return _read_generic(path, env, sidecar, cols, known)
    quat_cols = _quaternion_columns(cols, sidecar, path)
    actuator = str(sidecar.get("actuator", "thrust")).lower() if env == "quadrotor" else None
    act_cols = ACTUATOR_COLUMNS[actuator] if actuator else ()
    _require(cols, ("t", "x", "y", "z") + act_cols, path)
    for group in (VEL_COLUMNS, OMEGA_COLUMNS):
        present = [c for c in group if c in cols]
        if present and len(present) != 3:
            raise RispError(f"{path}: column(s) {', '.join(c for c in group if c not in cols)} missing (give all of {','.join(group)} or none)")
    frame = _omega_frame(env, cols, sidecar, path)
    _check_finite({k: v for k, v in cols.items() if k in known}, path)
    t = cols["t"]
    _check_time(t, path)
    _check_range(cols, ("x", "y", "z"), MAX_ABS_POSITION, "metres", path)
    _check_range(cols, VEL_COLUMNS, MAX_SPEED, "m/s", path)
    _check_range(cols, OMEGA_COLUMNS, MAX_ANGULAR_SPEED, "rad/s", path)
    _check_consistency(env, cols, sidecar, path)
    pos = np.stack([cols[c] for c in ("x", "y", "z")], 1)
    dpos = np.gradient(pos, t, axis=0)
    _check_position_speed(dpos, path)
    quat = _check_quat(np.stack([cols[c] for c in quat_cols], 1), path, quat_cols)
    vel_est = "vx" not in cols
    vel = dpos if vel_est else np.stack([cols[c] for c in VEL_COLUMNS], 1)
    om_est = "wx" not in cols
    omega = body_rates_from_quat(t, quat) if om_est else np.stack([cols[c] for c in OMEGA_COLUMNS], 1)
    if frame == "world":  # ω_body = Rᵀ ω_world
        omega = np.einsum("nji,nj->ni", quat_to_matrix_np(quat), omega)
    if not om_est:
        _check_rate_unit(omega, body_rates_from_quat(t, quat), path)
    thrust = command = None
    if actuator == "thrust":
        thrust = _delayed(t, np.stack([cols[c] for c in THRUST_COLUMNS], 1), sidecar)
    elif actuator == "collective":  # newtons, the whole vehicle
        command = _delayed(t, cols["thrust"][:, None], sidecar)
    elif actuator is not None:
        command = _delayed(t, _normalized_command(cols, act_cols, sidecar, path), sidecar)
    known = set(POSE_COLUMNS + VEL_COLUMNS + OMEGA_COLUMNS + act_cols + quat_cols)
    extra = {k: v for k, v in cols.items() if k not in known}
    return Trajectory(
        name=path.stem,
        path=str(path),
        t=t - t[0],
        pos=pos,
        quat=quat,
        vel=vel,
        omega=omega,
        thrust=thrust,
        command=command,
        sidecar=sidecar,
        vel_estimated=vel_est,
        omega_estimated=om_est,
        extra=extra,
    )


def _quaternion_columns(cols: dict, sidecar: Sidecar, path: Path) -> tuple[str, ...]:
    """Names of the (w, x, y, z) columns.  Named columns qw,qx,qy,qz are read by name; their header order
    must not contradict a declared ``quaternion_order``; numbered columns q0…q3 need the declaration."""
    order = sidecar.get("quaternion_order")
    order = None if order is None else str(order).lower()
    if all(c in cols for c in ("qw", "qx", "qy", "qz")):
        header = [c for c in cols if c in ("qw", "qx", "qy", "qz")]
        scalar_last = header == ["qx", "qy", "qz", "qw"]
        if order is not None and (order == "xyzw") != scalar_last:
            raise RispError(f"{path}: the header lists {','.join(header)} but the sidecar says quaternion_order "
                            f"{order!r}: ambiguous, make them agree")
        return ("qw", "qx", "qy", "qz")
    if all(c in cols for c in NUMBERED_QUAT):
        if order is None:
            raise RispError(f"{path}: columns q0..q3 without a sidecar 'quaternion_order' ('wxyz' scalar first or "
                            f"'xyzw' scalar last): refusing to guess")
        return NUMBERED_QUAT if order == "wxyz" else ("q3", "q0", "q1", "q2")
    _require(cols, ("qw", "qx", "qy", "qz"), path)
    return ()


def _omega_frame(env: str, cols: dict, sidecar: Sidecar, path: Path) -> str:
    """Frame of the wx,wy,wz columns: the sidecar's ``angular_velocity_frame``; a quadrotor file with rates
    must declare it (logs differ: PX4's vehicle_angular_velocity is body, some exports are world)."""
    frame = sidecar.get("angular_velocity_frame")
    if frame is None:
        if env == "quadrotor" and "wx" in cols:
            raise RispError(f"{path}: has columns wx,wy,wz but the sidecar does not say their frame: add "
                            f"\"angular_velocity_frame\": \"body\" or \"world\"")
        return "body"
    return str(frame).lower()


def _normalized_command(cols: dict, names: tuple[str, ...], sidecar: Sidecar, path: Path) -> np.ndarray:
    """(N, 4) rotor commands in [0, 1]: u columns as they are, PWM mapped by pwm_range [min, max]."""
    u = np.stack([cols[c] for c in names], 1)
    if names[0].startswith("pwm"):
        lo, hi = (float(v) for v in sidecar.get("pwm_range", [1000, 2000]))
        u = (u - lo) / (hi - lo)
    bad = np.flatnonzero((u < -0.05).any(1) | (u > 1.05).any(1))
    if bad.size:
        c = names[int(np.argmax((u[bad[0]] < -0.05) | (u[bad[0]] > 1.05)))]
        raise RispError(f"{path}: column {c} at data row {bad[0] + 1} is outside the normalised range [0, 1]"
                        + (" after pwm_range" if names[0].startswith("pwm") else "") + "; check the actuator declaration")
    return u


def _delayed(t: np.ndarray, u: np.ndarray, sidecar: Sidecar) -> np.ndarray:
    """Commands as the rotors see them: u(t − d) for the sidecar's ``actuator_delay`` d [s] (linear
    interpolation between samples, the first sample held before the start)."""
    d = float(sidecar.get("actuator_delay", 0.0) or 0.0)
    if d == 0.0:
        return u
    return np.stack([np.interp(t - d, t, u[:, i]) for i in range(u.shape[1])], 1)


def quat_to_matrix_np(q: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices (body -> world) of scalar-first unit quaternions (N, 4)."""
    w, x, y, z = q.T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def load_measured(paths, env: str, overrides: dict | None = None, limit: int | None = None) -> list[Trajectory]:
    """Read every CSV in ``paths`` (files or folders), validated; ``limit`` keeps the first N files."""
    if env not in SIDECAR_RANGES:
        raise RispError(f"unknown environment {env!r}; choose one of: {', '.join(SIDECAR_RANGES)}")
    files = expand_paths(list(paths))
    if limit is not None:
        if limit < 1:
            raise RispError(f"--limit must be at least 1, got {limit}")
        files = files[:limit]
    trajs = [read_trajectory(f, env, overrides) for f in files]
    _check_same_model(trajs, env)
    dts = np.array([tr.dt for tr in trajs])
    if dts.max() > 1.05 * dts.min():
        i, j = int(np.argmin(dts)), int(np.argmax(dts))
        raise RispError(
            f"sampling intervals differ between {trajs[i].path} ({dts[i]:g} s) and {trajs[j].path} ({dts[j]:g} s); "
            f"diagnose one sampling rate at a time"
        )
    return trajs


#: sidecar keys that define the model a file is simulated with (besides the simulator's own parameter names): all files
#: of one diagnosis must agree on them, as one model is fitted to all (per-file keys such as estimated_by may differ)
MODEL_KEYS = ("rotor_angles_deg", "rotor_spin", "pwm_range", "measurement_noise", "measurement_noise_correlation")
#: what an absent key means (so that "gravity": 9.81 in one file and no gravity in another agree)
SIDECAR_DEFAULTS = {"gravity": 9.81, "actuator": "thrust", "rotor_layout": "+", "thrust_map": "linear",
                    "measurement_noise_correlation": 0.0}


def _check_same_model(trajs: list[Trajectory], env: str) -> None:
    """One model is fitted to every file: files whose sidecars disagree on a physical value or a convention (a mass
    of 1.5 in one, 3.0 in another) are refused, naming the key and both files, rather than all simulated with the
    first file's."""
    from risp_tasks.sims import get_simulator

    keys = set(SIDECAR_RANGES.get(env, {})) | set(CHOICES) | set(MODEL_KEYS) | set(get_simulator(env).param_names)

    def value(tr, key):  # as the reader and the model take it: the default when absent, choices in any case
        v = tr.sidecar.values.get(key, SIDECAR_DEFAULTS.get(key))
        return str(v).lower() if key in CHOICES and v is not None else v

    first = trajs[0]
    for tr in trajs[1:]:
        for key in sorted(keys):
            a, b = value(first, key), value(tr, key)
            if a != b:
                raise RispError(f"{first.sidecar.source} and {tr.sidecar.source} disagree on sidecar key {key!r} "
                                f"({a!r} vs {b!r}): one model is fitted to all files; diagnose them separately")


def write_trajectory_csv(path: str | os.PathLike, traj_cols: dict[str, np.ndarray], sidecar: dict | None = None) -> None:
    """Write columns (and optionally ``<stem>.json``) atomically: temp name, then os.replace."""
    path = Path(path)
    names = list(traj_cols)
    data = np.stack([np.asarray(traj_cols[k], dtype=np.float64) for k in names], 1)
    with atomic_write(path, "w", suffix=".csv") as fh:
        w = csv.writer(fh)
        w.writerow(names)
        for row in data:
            w.writerow([repr(float(v)) for v in row])
    if sidecar is not None:
        write_text_atomic(path.with_suffix(".json"), json.dumps(sidecar, indent=2))
