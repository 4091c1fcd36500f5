"""Shard formats: round trips through the project readers AND the plain webdataset / zarr readers,
completion protocol, corrupt and truncated shards.  Arrays here are constructed (format tests); the
end-to-end tests with the real renderer live in tests/test_data_cli.py.
"""

from __future__ import annotations

import io
import json
import tarfile

import numpy as np
import pytest

from risp_data.errors import RispError
from risp_data.shards import (
    Sample,
    ZarrDataset,
    decode_wds_sample,
    iter_wds,
    load_manifest,
    verify_checksums,
    wds_urls,
)
from risp_data.shards.manifest import FORMAT_NAME, FORMAT_VERSION, read_marker, save_manifest
from risp_data.shards.writer import write_shard
from risp_data.shards.zarr_store import create_store

PSI = ["light_intensity", "object_r", "object_g"]
STATES = ["x", "y", "z"]
RES = 8


def _manifest(n, shard_size, formats=("wds", "zarr"), jacobian=True):
    return {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "env": "cube",
        "domain": "train",
        "resolution": RES,
        "spp": 2,
        "variant": "llvm_ad_rgb",
        "jacobian": jacobian,
        "n": n,
        "shard_size": shard_size,
        "num_shards": -(-n // shard_size),
        "seed": 7,
        "formats": list(formats),
        "psi": {"names": PSI, "nominal": [1, 0.5, 0.5], "low": [0, 0, 0], "high": [2, 1, 1]},
        "state_names": STATES,
        "shards": [],
    }


def _sample(i, rng, jacobian=True):
    return Sample(
        index=i,
        image=rng.random((RES, RES, 3), dtype=np.float32),
        jacobian=rng.standard_normal((len(PSI), RES, RES, 3)).astype(np.float32) if jacobian else None,
        state=rng.standard_normal(len(STATES)),
        psi=rng.random(len(PSI)),
        meta={"env": "cube", "index": i, "seed": 7, "psi_names": PSI, "state_names": STATES, "aux": {"k": [1, 2]}},
    )


def _write(folder, n=5, shard_size=2, formats=("wds", "zarr"), jacobian=True, skip=()):
    """Write a folder the way the render job does; returns {index: Sample}."""
    m = _manifest(n, shard_size, formats, jacobian)
    save_manifest(folder, m)
    if "zarr" in formats:
        create_store(folder, m)
    rng = np.random.default_rng(0)
    samples = {i: _sample(i, rng, jacobian) for i in range(n)}
    for s in range(m["num_shards"]):
        if s in skip:
            continue
        idx = range(s * shard_size, min((s + 1) * shard_size, n))
        m["shards"].append(write_shard(folder, tuple(formats), s, [samples[i] for i in idx]))
        save_manifest(folder, m)
    return samples


def _same(a: dict, s: Sample):
    np.testing.assert_array_equal(a["image"], s.image)
    np.testing.assert_array_equal(a["state"], s.state)
    np.testing.assert_array_equal(a["psi"], s.psi)
    if s.jacobian is None:
        assert a["jacobian"] is None
    else:
        np.testing.assert_array_equal(a["jacobian"], s.jacobian)


def test_wds_round_trip_project_reader(tmp_path):
    samples = _write(str(tmp_path))
    got = list(iter_wds(str(tmp_path)))
    assert [g["key"] for g in got] == [f"s{i:08d}" for i in range(5)]
    for g in got:
        _same(g, samples[g["meta"]["index"]])
        assert g["meta"]["aux"] == {"k": [1, 2]}
    m = load_manifest(str(tmp_path))
    assert m["complete"] and m["counts"]["complete_samples"] == 5
    assert verify_checksums(str(tmp_path)) == 3 * 5  # per shard: 1 tar + 4 zarr shard files


def test_wds_round_trip_plain_webdataset_and_openexr(tmp_path):
    import OpenEXR
    import webdataset as wds

    samples = _write(str(tmp_path))
    urls = sorted(str(p) for p in (tmp_path / "wds").glob("shard-*.tar"))
    assert len(urls) == 3
    raw = list(wds.WebDataset(urls, shardshuffle=False))
    assert len(raw) == 5
    for r in raw:
        i = int(r["__key__"][1:])
        assert set(k for k in r if not k.startswith("__")) == {"image.exr", "jacobian.exr", "json", "psi.npy", "state.npy"}
        meta = json.loads(r["json"])
        assert meta["index"] == i
        with OpenEXR.File(io.BytesIO(r["image.exr"])) as f:
            np.testing.assert_array_equal(f.channels()["RGB"].pixels, samples[i].image)
        with OpenEXR.File(io.BytesIO(r["jacobian.exr"])) as f:
            ch = f.channels()
            assert sorted(ch) == sorted(f"{p}.RGB" for p in PSI)
            for j, p in enumerate(PSI):
                np.testing.assert_array_equal(ch[f"{p}.RGB"].pixels, samples[i].jacobian[j])
        np.testing.assert_array_equal(np.load(io.BytesIO(r["psi.npy"]), allow_pickle=False), samples[i].psi)
        # the plain pipeline with the project decoder gives the same
        _same(decode_wds_sample(r), samples[i])


def test_zarr_round_trip_plain_zarr(tmp_path):
    import zarr

    samples = _write(str(tmp_path))
    g = zarr.open_group(str(tmp_path / "data.zarr"), mode="r")
    assert g.attrs["psi_names"] == PSI and g.attrs["state_names"] == STATES
    assert g["images"].shape == (5, RES, RES, 3) and g["images"].dtype == np.float32
    assert g["jacobians"].shape == (5, 3, RES, RES, 3)
    assert tuple(g["jacobians"].metadata.dimension_names) == ("sample", "psi", "y", "x", "channel")
    assert tuple(g["psi"].metadata.dimension_names) == ("sample", "psi")
    assert g["images"].shards == (2, RES, RES, 3)
    np.testing.assert_array_equal(g["images"][:], np.stack([samples[i].image for i in range(5)]))
    np.testing.assert_array_equal(g["jacobians"][3], samples[3].jacobian)
    np.testing.assert_array_equal(g["states"][:], np.stack([samples[i].state for i in range(5)]))
    ds = ZarrDataset(str(tmp_path))
    assert len(ds) == 5
    for i in range(5):
        _same(ds[i], samples[i])
    import copy

    clone = copy.deepcopy(ds)  # what DataLoader workers get: no open handles, reopened on first use
    assert clone._arrays is None
    _same(clone[-1], samples[4])
    with pytest.raises(IndexError):
        ds[5]


def test_incomplete_shards_are_invisible(tmp_path):
    samples = _write(str(tmp_path), skip=(1,))
    ds = ZarrDataset(str(tmp_path))
    assert len(ds) == 3 and [ds[i]["meta"]["index"] for i in range(3)] == [0, 1, 4]
    _same(ds[2], samples[4])
    assert [g["meta"]["index"] for g in iter_wds(str(tmp_path))] == [0, 1, 4]
    assert len(wds_urls(str(tmp_path))) == 2
    import zarr

    assert np.isnan(zarr.open_array(str(tmp_path / "data.zarr" / "images"), mode="r")[2]).all()  # fill value
    m = load_manifest(str(tmp_path))
    assert not m["complete"] and m["counts"]["complete_shards"] == 2


def test_marker_and_reproducible_tars(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    _write(str(a), formats=("wds",), jacobian=False)
    _write(str(b), formats=("wds",), jacobian=False)
    for name in ("shard-000000.tar", "shard-000002.tar"):
        assert (a / "wds" / name).read_bytes() == (b / "wds" / name).read_bytes()
    with tarfile.open(a / "wds" / "shard-000000.tar") as t:
        names = t.getnames()
        assert names == sorted(names) and all(m.mtime == 0 for m in t.getmembers())
        assert not any(n.endswith("jacobian.exr") for n in names)
    assert read_marker(str(a), 0)["stop"] == 2
    (a / "wds" / "shard-000000.tar").write_bytes(b"x")  # size no longer matches its marker
    assert read_marker(str(a), 0) is None
    assert [g["jacobian"] for g in iter_wds(str(b))] == [None] * 5


def _flip(path, offset):
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))


def test_truncated_tar_named(tmp_path):
    _write(str(tmp_path))
    p = tmp_path / "wds" / "shard-000001.tar"
    p.write_bytes(p.read_bytes()[:1500])
    with pytest.raises(RispError, match="shard-000001.tar"):
        list(iter_wds(str(tmp_path)))
    with pytest.raises(RispError, match="shard-000001.tar"):
        verify_checksums(str(tmp_path))


def test_corrupt_tar_member_named(tmp_path):
    import webdataset as wds

    _write(str(tmp_path))
    p = tmp_path / "wds" / "shard-000001.tar"
    with tarfile.open(p) as t:
        m = t.getmember("s00000002.image.exr")
        offset = m.offset_data + 200
    _flip(p, offset)
    with pytest.raises(RispError, match="corrupt shard file .*shard-000001.tar"):
        verify_checksums(str(tmp_path))
    # the reader on its own (no checksum pass) still names the shard and the key
    raw = [r for r in wds.WebDataset([str(p)], shardshuffle=False)]
    with pytest.raises(RispError, match=r"shard-000001\.tar key s00000002") as e:
        decode_wds_sample(raw[0])
    # and how to repair it, as every other reader's error says (the trainer's read gave no hint)
    assert str(e.value).endswith(f"; repair: risp-data verify --repair {tmp_path}"), str(e.value)
    with pytest.raises(RispError, match="shard-000001.tar"):
        list(iter_wds(str(tmp_path)))


def test_corrupt_and_truncated_zarr_shard_named(tmp_path):
    _write(str(tmp_path))
    p = tmp_path / "data.zarr" / "images" / "c" / "1" / "0" / "0" / "0"
    _flip(p, 40)  # inside the first inner chunk of shard 1 (sample 2)
    ds = ZarrDataset(str(tmp_path))
    with pytest.raises(RispError, match=r"data.zarr/images/c/1/0/0/0"):
        ds[2]
    p.write_bytes(p.read_bytes()[:-10])
    with pytest.raises(RispError, match=r"truncated or corrupt zarr shard file .*images/c/1/0/0/0"):
        ZarrDataset(str(tmp_path))


def test_the_machines_errors_are_not_called_corrupt_data(tmp_path, monkeypatch):
    """Out of memory, or a store this user may not read, is the machine's trouble: it reaches the command's own
    one-line messages as it is (risp_data.cli_util), not as 'corrupt … (repair it)', which would send the user to
    re-render good data."""
    import zarr

    import risp_data.shards.wds as wds

    _write(str(tmp_path))

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(zarr, "open_group", refuse)
    with pytest.raises(PermissionError):
        ZarrDataset(str(tmp_path))[0]
    monkeypatch.undo()

    def full(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(wds, "decode_exr", full)
    with pytest.raises(MemoryError):
        next(iter_wds(str(tmp_path)))


def test_missing_or_corrupt_manifest(tmp_path):
    with pytest.raises(RispError, match="not found"):
        load_manifest(str(tmp_path / "nope"))
    with pytest.raises(RispError, match="manifest not found"):
        load_manifest(str(tmp_path))
    (tmp_path / "manifest.json").write_text('{"format": "risp-shards", ')
    with pytest.raises(RispError, match="corrupt manifest"):
        load_manifest(str(tmp_path))
    (tmp_path / "manifest.json").write_text('{"format": "risp-shards"}')
    with pytest.raises(RispError, match="missing field"):
        wds_urls(str(tmp_path))


@pytest.mark.parametrize("field, value, words", [
    ("n", "abc", "field n is not a non-negative integer"),
    ("resolution", 64.5, "field resolution is not a non-negative integer"),
    ("seed", True, "field seed is not a non-negative integer"),
    ("env", 3, "field env is not a string"),
    ("jacobian", "yes", "field jacobian is not true or false"),
    ("formats", "wds", "field formats is not a list"),
    ("shards", [{"index": 0, "start": "0", "stop": 2, "files": {}}], "a record of field shards is malformed"),
])
def test_a_manifest_field_of_the_wrong_type_is_one_error(tmp_path, field, value, words):
    """A hand-edited manifest ("n": "abc") was a ValueError traceback in risp-train (inspect passed it): now
    load_manifest names the field."""
    _write(str(tmp_path))
    m = json.loads((tmp_path / "manifest.json").read_text())
    load_manifest(str(tmp_path))  # as written: valid
    m[field] = value
    (tmp_path / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(RispError, match=f"corrupt manifest .*: {words}"):
        load_manifest(str(tmp_path))


def test_atomic_write_gives_normal_permissions_and_cleans_up(tmp_path):
    """Files written through risp_data.atomic get umask permissions (not mkstemp's 0600); a failure
    leaves neither the target nor a temporary file behind."""
    import os
    import stat

    from risp_data.atomic import atomic_write

    path = tmp_path / "x.json"
    with atomic_write(str(path), "w") as f:
        f.write("{}")
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~mask
    with pytest.raises(RuntimeError):
        with atomic_write(str(tmp_path / "y.json"), "w") as f:
            f.write("half")
            raise RuntimeError("killed mid-write")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.json"]


def _first_raw_sample(folder, jacobian: bool) -> dict:
    """A written folder's first sample as webdataset hands it to decode_wds_sample (bytes per member)."""
    _write(str(folder), formats=("wds",), jacobian=jacobian)
    with tarfile.open(wds_urls(str(folder))[0]) as tar:
        members = {m.name: tar.extractfile(m).read() for m in tar.getmembers()}
    key = sorted(members)[0].split(".")[0]
    raw = {name.split(".", 1)[1]: data for name, data in members.items() if name.startswith(key + ".")}
    raw["__key__"], raw["__url__"] = key, "shard"
    return raw


def test_decode_without_jacobian_skips_it_but_still_checks_checksums(tmp_path):
    """decode_wds_sample(..., jacobian=False) returns no Jacobian, and a flipped byte in the
    undecoded jacobian.exr is still caught by its checksum."""
    raw = _first_raw_sample(tmp_path / "s", jacobian=True)
    full, lean = decode_wds_sample(raw), decode_wds_sample(raw, jacobian=False)
    assert full["jacobian"] is not None and lean["jacobian"] is None
    np.testing.assert_array_equal(full["image"], lean["image"])
    bad = dict(raw, **{"jacobian.exr": raw["jacobian.exr"][:-1] + bytes([raw["jacobian.exr"][-1] ^ 1])})
    with pytest.raises(RispError, match="sha256"):
        decode_wds_sample(bad, jacobian=False)


def test_an_image_of_another_size_is_refused_before_its_pixels_are_decoded(tmp_path, monkeypatch):
    """A small ZIP-compressed EXR expands to gigabytes (4096² from 212 KB): the readers decoded the whole image
    and only then compared its size with the manifest's.  The header is checked first, in every reader (here a
    consistent hostile sample: its member checksum matches the bigger image)."""
    import hashlib

    from risp_data.shards.wds import encode_exr

    raw = _first_raw_sample(tmp_path / "s", jacobian=False)
    raw["image.exr"] = encode_exr({"RGB": np.zeros((4 * RES, 4 * RES, 3), np.float32)})
    meta = json.loads(raw["json"])
    meta["member_sha256"]["image.exr"] = hashlib.sha256(raw["image.exr"]).hexdigest()
    raw["json"] = json.dumps(meta).encode()
    decoded = []
    import OpenEXR

    real = OpenEXR.File

    def counting(*a, header_only=False, **kw):
        if not header_only:
            decoded.append(1)
        return real(*a, header_only=header_only, **kw)

    monkeypatch.setattr(OpenEXR, "File", counting)
    with pytest.raises(RispError, match=rf"the EXR is {4 * RES}×{4 * RES} pixels, the folder's images {RES}×{RES}"):
        decode_wds_sample(raw, jacobian=False, resolution=RES)
    assert not decoded  # refused from the header alone
    assert decode_wds_sample(raw, jacobian=False)["image"].shape == (4 * RES, 4 * RES, 3)  # unchecked: decoded


def test_a_zarr_array_of_another_shape_than_the_manifests_is_refused(tmp_path):
    """The reader checked only that the arrays exist (the writer's check compares their shapes): a zarr.json
    edited to a larger shape made a read allocate that shape's fill value."""
    _write(str(tmp_path), formats=("zarr",))
    meta = tmp_path / "data.zarr" / "images" / "zarr.json"
    doc = json.loads(meta.read_text())
    doc["shape"] = [doc["shape"][0], 2 * RES, RES, 3]  # (larger ones allocate gigabytes without the check)
    meta.write_text(json.dumps(doc))
    with pytest.raises(RispError, match=rf"the array images has shape \(5, {2 * RES}, {RES}, 3\), the manifest's \("):
        ZarrDataset(str(tmp_path))[0]
