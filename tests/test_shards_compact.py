"""Own-channel Jacobian storage (issue 9): the default layout stores a material colour's ∂I/∂ψ_j as its own
channel only, where the other two are exactly +0.0 in that sample.  Checked here: plain webdataset / zarr
readers (the code of docs/formats.md) and the project's readers give back the same J, bit for bit, as the
full layout of the same seed; the trainer's loader gets the full (K, H, W, 3) stack; folders of the old
layout (format_version 1) are still read and resumed in their own layout; a sample whose off-channels are
not exactly +0.0 (even −0.0) keeps all three channels.  Real renders at tiny sizes (8×8, 2 spp)."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from click.testing import CliRunner

from risp_data.cli import cli
from risp_data.shards import ZarrDataset, iter_wds, load_manifest
from risp_data.shards.manifest import save_manifest

TINY = ["--env", "cube", "--res", "8", "--spp", "2", "--quiet", "--workers", "1"]
N = 4


def _render(out, *extra, n=N, shard_size=2):
    r = CliRunner().invoke(cli, ["render", *TINY, "--n", str(n), "--shard-size", str(shard_size), "--out", str(out),
                                 *extra])
    assert r.exit_code == 0, r.output + repr(r.exception)


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """The same seed rendered twice: default (own-channel) and --full-jacobian."""
    root = tmp_path_factory.mktemp("compact")
    _render(root / "own")
    _render(root / "full", "--full-jacobian")
    return str(root / "own"), str(root / "full")


# ----------------------------------------------------------------- the plain readers of docs/formats.md


def plain_wds_jacobians(folder):
    """docs/formats.md, "With plain webdataset": J per sample key, expanded from the EXR channels."""
    import OpenEXR
    import webdataset as wds

    urls = [f"{folder}/{rel}" for rec in json.load(open(f"{folder}/manifest.json"))["shards"]
            for rel in rec["files"] if rel.startswith("wds/")]
    out = {}
    for raw in wds.WebDataset(urls, shardshuffle=False):
        meta = json.loads(raw["json"])
        groups = OpenEXR.File(io.BytesIO(raw["jacobian.exr"])).channels()
        stored = meta.get("jacobian_channels", {})             # absent in full-layout samples: all "RGB"
        J = []
        for name in meta["psi_names"]:
            c = stored.get(name, "RGB")
            if c == "RGB":
                J.append(groups[f"{name}.RGB"].pixels)
            else:                                              # own channel only: the other two are +0.0
                j = np.zeros((*groups[f"{name}.{c}"].pixels.shape, 3), np.float32)
                j[..., "RGB".index(c)] = groups[f"{name}.{c}"].pixels
                J.append(j)
        out[raw["__key__"]] = np.stack(J)                      # (K, H, W, 3)
    return out


def plain_zarr_jacobian(folder, i):
    """docs/formats.md, "With plain zarr": the (K, H, W, 3) stack of sample i in either layout."""
    import zarr

    g = zarr.open_group(f"{folder}/data.zarr", mode="r")
    names = list(g.attrs["psi_names"])
    if "jacobians" in g:                                       # full layout
        return np.asarray(g["jacobians"][i])
    res = g.attrs["resolution"]
    J = np.zeros((len(names), res, res, 3), np.float32)
    for array in ("jacobian_planes", "jacobian_rest"):         # own-channel layout: every plane is listed
        planes = g[array][i]
        for p, (name, c) in enumerate(g[array].attrs["planes"]):
            J[names.index(name), :, :, "RGB".index(c)] = planes[p]
    return J


def _bits(a):
    return np.ascontiguousarray(a, np.float32).tobytes()


# ------------------------------------------------------------------------------------------- tests


def test_manifest_records_the_layout_and_the_files_hold_it(folders):
    import zarr

    own, full = (load_manifest(f) for f in folders)
    assert own["format_version"] == full["format_version"] == 2
    assert own["jacobian_storage"]["layout"] == "own-channel" and full["jacobian_storage"]["layout"] == "full"
    ch = own["jacobian_storage"]["channels"]
    assert ch["object_r"] == "R" and ch["floor_g"] == "G" and ch["floor_b"] == "B"
    assert ch["light_intensity"] == ch["ambient"] == "RGB"
    assert set(full["jacobian_storage"]["channels"].values()) == {"RGB"}
    g = zarr.open_group(f"{folders[0]}/data.zarr", mode="r")
    assert "jacobians" not in g and g["jacobian_planes"].shape == (N, 2 * 3 + 6, 8, 8)
    assert g["jacobian_rest"].shape == (N, 12, 8, 8)
    import webdataset as wds

    raw = next(iter(wds.WebDataset([f"{folders[0]}/wds/shard-000000.tar"], shardshuffle=False)))
    import OpenEXR

    names = set(OpenEXR.File(io.BytesIO(raw["jacobian.exr"])).channels())
    assert {"object_r.R", "object_g.G", "floor_b.B", "light_intensity.RGB"} <= names and "object_r.RGB" not in names


def test_plain_readers_give_the_full_layouts_j_bit_for_bit(folders):
    own, full = folders
    a, b = plain_wds_jacobians(own), plain_wds_jacobians(full)
    assert a.keys() == b.keys() and len(a) == N
    for key in a:
        assert _bits(a[key]) == _bits(b[key]), key
    for i in range(N):
        assert _bits(plain_zarr_jacobian(own, i)) == _bits(plain_zarr_jacobian(full, i)) == _bits(b[f"s{i:08d}"])
    # the colour ψ really are stored compactly (no fall-back happened), and J is not trivially zero
    assert not any("jacobian_fallback" in r for r in load_manifest(own)["shards"])
    assert all(np.abs(b[k]).max() > 0 for k in b)


def test_project_readers_and_the_trainer_get_the_full_stack(folders):
    from risp_train.data import iter_batches, make_loader, open_shards

    own, full = folders
    zo, zf = ZarrDataset(own), ZarrDataset(full)
    wo, wf = list(iter_wds(own)), list(iter_wds(full))
    for i in range(N):
        assert zo[i]["jacobian"].shape == (8, 8, 8, 3)
        assert _bits(zo[i]["jacobian"]) == _bits(zf[i]["jacobian"]) == _bits(wo[i]["jacobian"]) == _bits(wf[i]["jacobian"])
    for fmt in ("wds", "zarr"):
        got = [next(iter_batches(open_shards(f, fmt), N, need_jacobian=True))["jacobian"] for f in folders]
        assert got[0].shape == (N, 8, 8, 8, 3) and _bits(got[0].numpy()) == _bits(got[1].numpy()), fmt
        loaders = [make_loader(open_shards(f, fmt), seed=3, epoch=0, batch_size=2, workers=0, need_jacobian=True)
                   for f in folders]
        for x, y in zip(*loaders):
            assert _bits(x["jacobian"].numpy()) == _bits(y["jacobian"].numpy()), fmt


def test_verify_and_inspect_work_on_the_compact_layout(folders):
    r = CliRunner().invoke(cli, ["verify", folders[0], "--samples", "2"])
    assert r.exit_code == 0 and "FAIL" not in r.output, r.output
    r = CliRunner().invoke(cli, ["inspect", folders[0], "--deep"])
    assert r.exit_code == 0 and "own-channel" in r.output and f"{N}/{N} complete" in r.output, r.output


def test_old_layout_folder_is_read_and_resumed_in_its_own_layout(tmp_path, folders):
    """A format_version-1 folder (no jacobian_storage) with one shard missing: read as before, and the
    default (own-channel) render command completes it in the full layout it has."""
    import shutil

    import zarr

    old = str(tmp_path / "old")
    shutil.copytree(folders[1], old)
    m = load_manifest(old)
    del m["jacobian_storage"]
    m["format_version"] = 1
    m["shards"] = [r for r in m["shards"] if r["index"] == 0]
    save_manifest(old, m)
    assert len(ZarrDataset(old)) == 2 and len(list(iter_wds(old))) == 2
    _render(old)  # the user's command, default layout: resumes shard 1 in the folder's (full) layout
    assert "jacobian_planes" not in zarr.open_group(f"{old}/data.zarr", mode="r")
    ref = ZarrDataset(folders[1])
    for ds in (ZarrDataset(old), list(iter_wds(old))):
        for i in range(N):
            assert _bits(ds[i]["jacobian"]) == _bits(ref[i]["jacobian"]), i


def test_a_sample_whose_other_channels_are_not_plus_zero_keeps_all_three(tmp_path):
    """Per-sample exactness: sample 1 has a non-zero G channel in ∂I/∂object_r and sample 2 a −0.0; both keep
    object_r in full (wds json, zarr fall-back record) and every reader restores the exact bits."""
    from risp_data.shards import Sample
    from risp_data.shards.layout import storage_block
    from risp_data.shards.writer import write_shard
    from risp_data.shards.zarr_store import create_store
    from tests.test_shards import PSI, _manifest, _sample

    folder = str(tmp_path)
    m = _manifest(3, 3)
    m["jacobian_storage"] = storage_block(PSI, {"object_r": "R", "object_g": "G"}, compact=True)
    save_manifest(folder, m)
    create_store(folder, m)
    rng = np.random.default_rng(1)
    samples = []
    for i in range(3):
        s = _sample(i, rng)
        jac = s.jacobian.copy()
        jac[1][..., 1:] = 0.0
        jac[2][..., [0, 2]] = 0.0
        if i == 1:
            jac[1][3, 4, 1] = 1e-3
        if i == 2:
            jac[1][0, 0, 2] = -0.0
        samples.append(Sample(s.index, s.image, jac, s.state, s.psi, s.meta))
    m["shards"] = [write_shard(folder, ("wds", "zarr"), 0, samples)]
    save_manifest(folder, m)
    assert m["shards"][0]["jacobian_fallback"] == {"1": ["object_r"], "2": ["object_r"]}
    metas = [s["meta"]["jacobian_channels"] for s in iter_wds(folder)]
    assert [x["object_r"] for x in metas] == ["R", "RGB", "RGB"] and all(x["object_g"] == "G" for x in metas)
    zs, ws, plain = ZarrDataset(folder), list(iter_wds(folder)), plain_wds_jacobians(folder)
    for i, s in enumerate(samples):
        want = _bits(s.jacobian)
        assert _bits(zs[i]["jacobian"]) == _bits(ws[i]["jacobian"]) == _bits(plain[s.key]) == want, i
        assert _bits(plain_zarr_jacobian(folder, i)) == want, i
