"""The look fingerprint (risp_data.envs.look): rendered data, its folders and the tables' cells are tied to the
appearance they were made with, so a changed look never mixes with work made under an old one."""

import json

import pytest
from click.testing import CliRunner

from risp_data.cli import cli
from risp_data.envs import ENV_NAMES, materials
from risp_data.envs import look as look_module
from risp_data.shards import load_manifest


@pytest.fixture
def fresh_looks():
    look_module.look_fingerprint.cache_clear()
    yield
    look_module.look_fingerprint.cache_clear()


def test_fingerprint_is_stable_distinct_and_follows_the_appearance(fresh_looks, monkeypatch):
    looks = {e: look_module.look_fingerprint(e) for e in ENV_NAMES}
    assert len(set(looks.values())) == len(ENV_NAMES) and all(len(v) == 12 for v in looks.values())
    look_module.look_fingerprint.cache_clear()
    assert {e: look_module.look_fingerprint(e) for e in ENV_NAMES} == looks  # recomputed: the same
    # a sticker's colour is part of the cube's look and of no other environment's
    monkeypatch.setitem(materials.FIXED_MATERIALS, "sticker1", (0.1, 0.8, 0.1))
    look_module.look_fingerprint.cache_clear()
    changed = {e: look_module.look_fingerprint(e) for e in ENV_NAMES}
    assert changed["cube"] != looks["cube"]
    assert all(changed[e] == looks[e] for e in ENV_NAMES if e != "cube")


def _render(out, n=2):
    return CliRunner().invoke(cli, ["render", "--env", "cube", "--res", "8", "--spp", "1", "--quiet", "--n", str(n),
                                    "--shard-size", "1", "--workers", "1", "--format", "wds", "--out", str(out)])


def test_folder_of_another_look_is_not_resumed(tmp_path, fresh_looks, monkeypatch):
    out = tmp_path / "cube"
    r = _render(out, n=2)
    assert r.exit_code == 0, r.output
    m = load_manifest(str(out))
    assert m["look"] == look_module.look_fingerprint("cube")
    # an incomplete folder rendered with an older look (simulated: its manifest says so) must not be completed
    # with images of today's look
    m["look"] = "0123456789ab"
    m["n"] = 3
    with open(out / "manifest.json", "w") as f:
        json.dump(m, f)
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    r = _render(out, n=3)
    assert r.exit_code == 1
    assert r.output.strip().splitlines()[-1].startswith("Error: output folder")
    assert "look='0123456789ab' (folder)" in r.output
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()} == before


def test_table_cells_of_another_look_are_recomputed(tmp_path):
    from risp_tasks.tables.grid import Cell, cell_look, read_cell

    cell = Cell("cube", "average", 0)
    path = tmp_path / "r0.json"
    path.write_text(json.dumps({"value": 1.0, "look": cell_look(cell)}))
    assert read_cell(str(path), cell_look(cell))["value"] == 1.0
    path.write_text(json.dumps({"value": 1.0, "look": "0123456789ab"}))
    assert read_cell(str(path), cell_look(cell)) is None
    path.write_text(json.dumps({"value": 1.0}))  # a cell from before looks were recorded
    assert read_cell(str(path), cell_look(cell)) is None


def test_verify_refuses_a_folder_of_another_look(tmp_path):
    out = tmp_path / "cube"
    assert _render(out, n=1).exit_code == 0
    m = load_manifest(str(out))
    m["look"] = "0123456789ab"
    with open(out / "manifest.json", "w") as f:
        json.dump(m, f)
    r = CliRunner().invoke(cli, ["verify", str(out), "--samples", "1", "--no-checksums"])
    assert r.exit_code == 1 and "rendered with another look of cube" in r.output.strip().splitlines()[-1]


def test_folder_from_before_looks_were_recorded_still_reads(tmp_path):
    """Old folders (no "look" in the manifest) are read and trained on; only resuming them is refused."""
    from risp_train.data import open_shards

    out = tmp_path / "cube"
    assert _render(out, n=2).exit_code == 0
    m = load_manifest(str(out))
    del m["look"]
    with open(out / "manifest.json", "w") as f:
        json.dump(m, f)
    assert "look" not in load_manifest(str(out))
    assert open_shards(str(out)).manifest["n"] == 2
    r = _render(out, n=2)
    assert r.exit_code == 1 and "look=None (folder)" in r.output


def test_checkpoint_records_the_look_and_the_render_loss_warns_on_another(tmp_path_factory):
    from risp_tasks.tasks.inputs import load_model, look_note
    from tasks_helpers import shared_model  # the same module (and cache) as the task tests, not a second copy

    path = shared_model(tmp_path_factory, "cube")
    predictor = load_model(path, "cube")
    assert predictor.look == look_module.look_fingerprint("cube")
    assert look_note(predictor, path, "render", None) is None
    predictor.look = "0123456789ab"  # a network trained on images of an older look
    note = look_note(predictor, path, "render", None)
    assert note.startswith("note: ") and "another look (0123456789ab)" in note
    assert look_note(predictor, path, "state", None) is None  # no rendered image reaches N
    assert look_note(predictor, path, "render", "vehicle.obj") is None  # the user's own mesh: their look
