"""Manifest truth (issue 9): a folder's ψ block describes the ranges ψ was sampled from in that folder's
domain, with units, and says what J is differentiated with respect to."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from risp_data.envs import ENV_NAMES
from risp_data.psi import DOMAINS, JACOBIAN_MEANING, psi_manifest, psi_specs, sample_rendering
from tests.shard_helpers import scale_stored_jacobian


def _inside(value: float, intervals) -> bool:
    return any(a <= value <= b for a, b in intervals)


@pytest.mark.parametrize("domain", DOMAINS)
@pytest.mark.parametrize("env", ENV_NAMES)
def test_specs_hold_every_sampled_psi_of_their_domain(env, domain):
    specs = psi_specs(env, domain)
    rng = np.random.default_rng(1)
    psis = np.array([sample_rendering(env, domain, rng).psi for _ in range(400)])
    for j, s in enumerate(specs):
        assert s.unit and s.description and s.intervals
        assert s.low == min(a for a, _ in s.intervals) and s.high == max(b for _, b in s.intervals)
        assert all(_inside(v, s.intervals) for v in psis[:, j]), s.name
        # the intervals are tight: samples reach near both ends of the hull
        assert psis[:, j].min() - s.low < 0.05 * (s.high - s.low) and s.high - psis[:, j].max() < 0.05 * (s.high - s.low)


def test_target_colour_ranges_lie_outside_the_training_ranges():
    train, target = psi_specs("cube", "train"), psi_specs("cube", "target")
    for tr, tg in zip(train, target):
        assert tr.name == tg.name
        if tr.name.startswith(("object_", "floor_")):
            assert len(tg.intervals) == 2
            (a, b), (c, d) = tg.intervals
            assert b <= tr.low and c >= tr.high  # below or above, never inside
            assert tg.low < tr.low and tg.high > tr.high
    assert target[0].low == 1.0 and target[0].high == 3.0  # light_intensity
    assert train[1].description != target[1].description  # ambient: constant radiance vs sky-map scale
    assert train[1].unit != target[1].unit


def test_manifest_block_states_domain_units_and_jacobian_meaning():
    m = psi_manifest("quadrotor", "target")
    assert m["domain"] == "target" and m["jacobian"] == JACOBIAN_MEANING
    assert "raw" in m["jacobian"] and "no normalisation" in m["jacobian"]
    K = len(m["names"])
    for key in ("nominal", "low", "high", "intervals", "train_low", "train_high", "descriptions", "units"):
        assert len(m[key]) == K, key
    assert m["low"] != m["train_low"]
    json.dumps(m, allow_nan=False)  # JSON-serialisable


def test_target_folder_manifest_lists_target_ranges(tmp_path):
    from risp_data.cli import cli
    from risp_data.shards import load_manifest

    out = tmp_path / "t"
    args = ["render", "--env", "cube", "--domain", "target", "--res", "8", "--spp", "1", "--quiet", "--n", "1",
            "--shard-size", "1", "--workers", "1", "--format", "wds", "--out", str(out)]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    m = load_manifest(str(out))["psi"]
    target = psi_specs("cube", "target")
    assert m["domain"] == "target"
    assert m["low"] == [s.low for s in target] and m["high"] == [s.high for s in target]
    assert m["descriptions"] == [s.description for s in target]
    assert m["train_low"] == [s.low for s in psi_specs("cube", "train")]
    assert m["units"][0].startswith("dimensionless multiple")


def test_verify_default_tolerance_catches_a_jacobian_off_by_half_a_percent(tmp_path):
    """The old default (0.05) let a 0.5 % wrong J through; the new one (1e-3, docs/cli-data.md) fails it,
    while the untouched folder passes at the new default."""
    from risp_data.cli import cli
    from risp_data.shards import load_manifest
    from risp_data.shards.manifest import file_record, save_manifest
    from risp_data.verify import TOL, VerifyConfig, verify_folder

    out = tmp_path / "v"
    args = ["render", "--env", "cube", "--res", "8", "--spp", "2", "--quiet", "--n", "2", "--shard-size", "2",
            "--workers", "1", "--format", "zarr", "--out", str(out)]
    assert CliRunner().invoke(cli, args).exit_code == 0
    ok = verify_folder(VerifyConfig(str(out), samples=2, progress=False))
    assert not ok.failures and max(ok.rel_error) < TOL / 10, ok.rel_error
    m = load_manifest(str(out))
    scale_stored_jacobian(str(out), [0, 1], "object_g", 1.005)
    rec = m["shards"][0]
    rec["files"] = {rel: file_record(str(out), rel) for rel in rec["files"]}
    save_manifest(str(out), m)
    assert not verify_folder(VerifyConfig(str(out), samples=2, tol=0.05, progress=False)).failures
    bad = verify_folder(VerifyConfig(str(out), samples=2, progress=False))
    assert len(bad.failures) == 1 and "object_g" in bad.failures[0]


def _wrap_jumps(w: np.ndarray) -> tuple[float, float, float, float]:
    """(largest |jump| across the x wrap, largest between neighbouring columns, same for y)."""
    dx, dy = np.abs(np.diff(w, axis=1)), np.abs(np.diff(w, axis=0))
    return (float(np.abs(w[:, 0] - w[:, -1]).max()), float(dx.max()),
            float(np.abs(w[0] - w[-1]).max()), float(dy.max()))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_target_wood_floor_tiles_seamlessly(seed):
    """Mitsuba repeats the floor texture (wrap_mode repeat, bilinear): the step across the texture's
    edge must be no larger than the steps inside it, for x and y."""
    from risp_data.render import floor_texture

    w, c0, c1 = floor_texture("wood", seed)
    assert w.dtype == np.float32 and 0 <= w.min() and w.max() <= 1 and w.std() > 0.1  # a pattern, not flat
    wrap_x, inner_x, wrap_y, inner_y = _wrap_jumps(w.astype(np.float64))
    assert wrap_x <= inner_x * 1.01 and wrap_y <= inner_y * 1.01
    # the test can fail: the old ring pattern's seam is several inner steps high
    yy, xx = np.mgrid[0:64, 0:64] / 64
    old = 0.5 + 0.5 * np.sin(np.sqrt((xx - 0.3) ** 2 * 0.2 + (yy - 0.5) ** 2) * 30 + 2 * np.sin(xx * 6 + 1.0))
    ox, oix, _, _ = _wrap_jumps(old)
    assert ox > 2 * oix
