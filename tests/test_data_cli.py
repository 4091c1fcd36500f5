"""risp-data end to end with the REAL renderer (tiny sizes): render -> shards -> inspect / verify,
determinism, resume after a kill, and every bad-input case of issue 2 item 7.

Determinism tolerance: on this machine (LLVM backend) the samples came out bit-identical across runs,
worker counts and shard sizes; the tests compare with np.testing.assert_allclose(rtol=1e-5, atol=1e-6)
for the images and Jacobians (docs/formats.md, "Determinism") and exactly for states and ψ.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from click.testing import CliRunner

from risp_data.cli import cli
from risp_data.shards import ZarrDataset, iter_wds, load_manifest
from tests.shard_helpers import scale_stored_jacobian

TINY = ["--env", "cube", "--res", "8", "--spp", "2", "--quiet"]


def _render(out, *extra, n=4, shard_size=2, workers=1):
    args = ["render", *TINY, "--n", str(n), "--shard-size", str(shard_size), "--workers", str(workers), "--out", str(out)]
    return CliRunner().invoke(cli, [*args, *extra])


def _ok(result):
    assert result.exit_code == 0, result.output + repr(result.exception)
    return result


def _error_line(result, pattern):
    assert result.exit_code != 0
    lines = [ln for ln in result.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.output
    assert pattern in lines[0], lines[0]


def _samples(folder):
    """{index: sample} from both readers, checking that they agree."""
    z = ZarrDataset(str(folder))
    zs = {z[i]["meta"]["index"]: z[i] for i in range(len(z))}
    ws = {s["meta"]["index"]: s for s in iter_wds(str(folder))}
    assert zs.keys() == ws.keys()
    for i in zs:
        np.testing.assert_array_equal(zs[i]["image"], ws[i]["image"])
        np.testing.assert_array_equal(zs[i]["jacobian"], ws[i]["jacobian"])
        np.testing.assert_array_equal(zs[i]["psi"], ws[i]["psi"])
    return zs


def _assert_same(a, b):
    assert a.keys() == b.keys()
    for i in a:
        np.testing.assert_array_equal(a[i]["state"], b[i]["state"])
        np.testing.assert_array_equal(a[i]["psi"], b[i]["psi"])
        np.testing.assert_allclose(a[i]["image"], b[i]["image"], rtol=1e-5, atol=1e-6)
        if a[i]["jacobian"] is None:
            assert b[i]["jacobian"] is None
        else:
            np.testing.assert_allclose(a[i]["jacobian"], b[i]["jacobian"], rtol=1e-5, atol=1e-6)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """One small folder shared by the read-only tests: 5 cube samples, shards of 2, both formats."""
    out = tmp_path_factory.mktemp("shards") / "cube"
    _ok(_render(out, n=5))
    return out


def test_render_writes_both_formats_and_manifest(rendered):
    m = load_manifest(str(rendered))
    assert m["complete"] and m["counts"]["complete_samples"] == 5 and m["num_shards"] == 3
    assert m["env"] == "cube" and m["resolution"] == 8 and m["spp"] == 2 and m["seed"] == 0
    assert len(m["psi"]["names"]) == len(m["psi"]["low"]) == len(m["psi"]["nominal"]) >= 6
    assert set(m["versions"]) >= {"risp", "mitsuba", "drjit", "torch", "numpy", "zarr", "webdataset", "OpenEXR"}
    for rec in m["shards"]:
        assert all(len(f["sha256"]) == 64 for f in rec["files"].values())
    s = _samples(rendered)
    assert sorted(s) == list(range(5))
    k = len(m["psi"]["names"])
    assert s[0]["image"].shape == (8, 8, 3) and s[0]["jacobian"].shape == (k, 8, 8, 3)
    assert np.isfinite(s[4]["jacobian"]).all() and np.abs(s[4]["jacobian"]).max() > 0
    assert not any(n.startswith(".tmp-") for n in os.listdir(rendered / "wds"))


def test_inspect_prints_summary_and_writes_png(rendered, tmp_path):
    png = tmp_path / "sheet.png"
    r = _ok(CliRunner().invoke(cli, ["inspect", str(rendered), "--png", str(png), "--samples", "2"]))
    assert "cube" in r.output and "5/5 complete" in r.output and "light_intensity" in r.output
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_folder_of_data_sets_is_named_not_called_missing(rendered, tmp_path):
    """inspect/verify (and everything that reads a manifest) given a parent folder, such as the default
    shards/, list the data sets in it instead of saying that a manifest is missing."""
    import shutil

    parent = tmp_path / "shards"
    for name in ("cube-train", "cube-target"):
        shutil.copytree(rendered, parent / name)
    for cmd in (["inspect", str(parent)], ["verify", str(parent)]):
        r = CliRunner().invoke(cli, cmd)
        _error_line(r, "holds 2")
        assert "cube-target" in r.output and "cube-train" in r.output and "pass one of them" in r.output
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(Exception, match="manifest not found"):  # a folder with no data set at all: as before
        load_manifest(str(empty))
    video = tmp_path / "video.mp4"  # a file given where a folder is meant: not called missing either
    video.write_bytes(b"\x00" * 16)
    _error_line(CliRunner().invoke(cli, ["inspect", str(video)]), "is a file, not a shard folder")


def test_verify_passes_then_fails_on_tampered_jacobian(tmp_path):
    out = tmp_path / "v"
    _ok(_render(out, n=2, shard_size=2))
    r = _ok(CliRunner().invoke(cli, ["verify", str(out), "--samples", "2"]))
    # one tar + the zarr shard files of images, jacobian_planes, jacobian_rest, states, psi
    assert "checksums: 6 shard files ok" in r.output and "FAIL" not in r.output
    # tamper one psi's stored Jacobian of sample 1 (zarr is what verify reads when present) ...
    m = load_manifest(str(out))
    rel = scale_stored_jacobian(str(out), [1], "light_intensity", 1.5)
    # ... the file no longer matches its checksum: verify names it
    r = CliRunner().invoke(cli, ["verify", str(out), "--samples", "2"])
    _error_line(r, rel)
    # ... and with a manifest that agrees with the bytes (as if the writer had stored a wrong J),
    # the central-difference check catches it
    from risp_data.shards.manifest import file_record, save_manifest

    rec = m["shards"][0]
    rec["files"] = {rel: file_record(str(out), rel) for rel in rec["files"]}
    save_manifest(str(out), m)
    r = CliRunner().invoke(cli, ["verify", str(out), "--samples", "2"])
    assert r.exit_code == 1
    assert "light_intensity" in r.output and "FAIL" in r.output
    last = r.output.strip().splitlines()[-1]
    assert last.startswith("Error: verify failed") and "light_intensity rel. error" in last
    assert "object_r rel. error" not in last
    # a stored NaN fails too (a NaN compares False with every tolerance: it used to pass)
    rel = scale_stored_jacobian(str(out), [0], "light_intensity", float("nan"))
    rec["files"] = {r_: file_record(str(out), r_) for r_ in rec["files"]}
    save_manifest(str(out), m)
    r = CliRunner().invoke(cli, ["verify", str(out), "--samples", "2"])
    assert r.exit_code == 1 and "sample 0: the stored image or Jacobian holds NaN or inf" in r.output, r.output
    # both samples unusable: no ψ line may say "ok" of Jacobians that were never compared
    rel = scale_stored_jacobian(str(out), [1], "light_intensity", float("nan"))
    rec["files"] = {r_: file_record(str(out), r_) for r_ in rec["files"]}
    save_manifest(str(out), m)
    r = CliRunner().invoke(cli, ["verify", str(out), "--samples", "2"])
    assert r.exit_code == 1 and "chosen samples [0, 1]: none compared" in r.output, r.output
    assert " ok" not in r.output.replace("shard files ok", "")


@pytest.mark.parametrize("fmt", ["wds", "zarr"])
def test_single_format_folders_inspect_and_verify(tmp_path, fmt):
    out = tmp_path / fmt
    _ok(_render(out, "--format", fmt, n=2, shard_size=2))
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == sorted(
        ["manifest.json", "complete", "wds" if fmt == "wds" else "data.zarr"]
    )
    r = _ok(CliRunner().invoke(cli, ["inspect", str(out), "--samples", "1"]))
    assert (out / "contact_sheet.png").exists() and f"formats      {fmt}" in r.output
    r = _ok(CliRunner().invoke(cli, ["verify", str(out), "--samples", "1", "--no-checksums"]))
    assert "FAIL" not in r.output and "checksums: skipped" in r.output


def test_determinism_across_shard_size_and_workers(rendered, tmp_path):
    a = _samples(rendered)
    _ok(_render(tmp_path / "b", n=5, shard_size=3))
    _assert_same(a, _samples(tmp_path / "b"))
    _ok(_render(tmp_path / "c", n=5, shard_size=2, workers=2))  # process pool (fork server)
    _assert_same(a, _samples(tmp_path / "c"))
    for rec_a, rec_c in zip(load_manifest(str(rendered))["shards"], load_manifest(str(tmp_path / "c"))["shards"]):
        assert rec_a["start"] == rec_c["start"]
    _ok(_render(tmp_path / "d", "--seed", "1", n=2))
    assert not np.array_equal(_samples(tmp_path / "d")[0]["psi"], a[0]["psi"])


def _files_of(folder, rec):
    return {rel: (os.stat(folder / rel).st_mtime_ns, os.stat(folder / rel).st_ino) for rel in rec["files"]}


def test_resume_after_kill(tmp_path):
    # images only: the resume protocol does not depend on the Jacobians, and this keeps the test short
    out = tmp_path / "r"
    n, size = 40, 2
    cmd = [sys.executable, "-m", "risp_data", "render", *TINY, "--n", str(n), "--shard-size", str(size),
           "--workers", "1", "--no-jacobian", "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    try:
        while time.time() < deadline:
            try:
                if load_manifest(str(out))["counts"]["complete_shards"] >= 1:
                    break
            except Exception:  # not there yet
                pass
            assert proc.poll() is None, proc.stderr.read()
            time.sleep(0.01)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait()
    m1 = load_manifest(str(out))
    done = {r["index"]: _files_of(out, r) for r in m1["shards"]}
    assert 1 <= len(done) < n // size, "the run should have been killed part-way"
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    # a shard whose marker was written just before the kill (manifest not yet updated) also counts as done
    log = re.search(r"(\d+) of (\d+) shards complete, rendering (\d+)", r.stderr)
    assert log, r.stderr
    kept, total, rendered_now = map(int, log.groups())
    assert total == n // size and kept >= len(done) and rendered_now == total - kept
    m2 = load_manifest(str(out))
    assert m2["complete"]
    for rec in m2["shards"]:
        if rec["index"] in done:  # complete shards were not rewritten
            assert _files_of(out, rec) == done[rec["index"]]
    assert not any(name.startswith(".tmp-") for name in os.listdir(out / "wds"))
    # equals an uninterrupted run
    _ok(_render(tmp_path / "u", "--no-jacobian", n=n, shard_size=size))
    _assert_same(_samples(tmp_path / "u"), _samples(out))


def test_ctrl_c_stops_a_worker_pool_render_now(tmp_path):
    """SIGINT to a `--workers 2` render: the workers stop at once (exit 130 in seconds) rather than first finishing
    the shards already queued to them (about a minute each here), and no shard is marked complete."""
    out = tmp_path / "int"
    cmd = [sys.executable, "-m", "risp_data", "render", "--env", "cube", "--res", "64", "--spp", "256", "--quiet",
           "--no-jacobian", "--n", "600", "--shard-size", "300", "--workers", "2", "--out", str(out)]
    # SIGINT's default action restored (a background job of a non-interactive shell inherits it ignored)
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.time() + 120
        while not (out / "manifest.json").exists() and time.time() < deadline and proc.poll() is None:
            time.sleep(0.2)
        time.sleep(5)  # the workers start rendering
        done_before = _markers(out)
        proc.send_signal(signal.SIGINT)  # to the job alone, as `kill -INT`: the workers must be stopped by it
        _, err = proc.communicate(timeout=45)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130 and "Error: interrupted" in err, (proc.returncode, err)
    # no shard finished after the interrupt (without the fix each worker completed the shard it had; on a machine
    # fast enough to finish shards before the signal, those are simply kept)
    assert _markers(out) == done_before


def _markers(out):
    return sorted(p.name for p in (out / "complete").glob("*")) if (out / "complete").exists() else []


def test_a_render_that_will_not_fit_on_its_disk_stops_keeping_its_shards(tmp_path, monkeypatch):
    """After a shard is written, the samples still to render (at its bytes per sample) are compared with the free
    space: a render that cannot fit stops with one line and keeps its finished shards, instead of filling the disk."""
    import shutil as _shutil

    import risp_data.generate as generate

    out = tmp_path / "big"
    monkeypatch.setattr(generate.shutil, "disk_usage", lambda p: _shutil._ntuple_diskusage(10**12, 10**12, 0))
    r = _render(out, "--no-jacobian", n=6, shard_size=2)
    lines = [ln for ln in r.output.splitlines() if ln.startswith("Error:")]
    assert r.exit_code == 1 and len(lines) == 1, r.output
    assert "the 4 samples still to render need about" in lines[0] and "finished shard(s) are kept" in lines[0]
    assert load_manifest(str(out))["counts"]["complete_shards"] == 1
    monkeypatch.undo()
    _ok(_render(out, "--no-jacobian", n=6, shard_size=2))  # resumes once there is room
    assert load_manifest(str(out))["complete"]


# ------------------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize(
    "args, message",
    [
        (["--env", "cubee"], "Invalid value for '--env': 'cubee' is not one of 'quadrotor', 'cube', 'hand', 'rod'"),
        (["--domain", "space"], "Invalid value for '--domain': 'space' is not one of 'train', 'target'"),
        (["--n", "0"], "--n must be a positive integer"),
        (["--n", "-3"], "--n must be a positive integer"),
        (["--format", "hdf5"], "Invalid value for '--format': 'hdf5' is not one of 'wds', 'zarr', 'both'"),
        (["--executor", "slurm"], "Invalid value for '--executor': 'slurm' is not one of 'local', 'ray'"),
        (["--jacobian-path", "slow"], "Invalid value for '--jacobian-path': 'slow' is not one of 'fast', 'legacy'"),
    ],
)
def test_bad_arguments(tmp_path, capsys, args, message):  # without Ray: test_ray_executor_without_ray_is_one_line
    options = {"--env": "cube", "--n": "2", "--res": "8", "--spp": "2", "--out": str(tmp_path / "o")}
    options.update(zip(args[::2], args[1::2]))
    _entry_point_error(["render", *[a for kv in options.items() for a in kv]], capsys, message)
    assert not (tmp_path / "o").exists()


def _entry_point_error(argv, capsys, pattern):
    """The console script's behaviour (run_cli, not CliRunner): one 'Error:' line on stderr, status 1."""
    from tests.cli_helpers import console_error_line

    line = console_error_line(cli, argv, capsys)
    assert pattern in line, line


def test_contradicting_jacobian_flags_and_a_huge_fd_step_are_refused(tmp_path):
    r = CliRunner().invoke(cli, ["render", "--env", "cube", "--n", "2", "--res", "8", "--spp", "2", "--out",
                                 str(tmp_path / "o"), "--no-jacobian", "--full-jacobian"])
    _error_line(r, "--full-jacobian sets how Jacobians are stored; --no-jacobian renders none")
    assert not (tmp_path / "o").exists()
    from risp_data.errors import RispError
    from risp_data.verify import VerifyConfig, verify_folder

    r = CliRunner().invoke(cli, ["inspect", str(tmp_path), "--png", str(tmp_path / "sheet.jpg")])
    _error_line(r, "the contact sheet is a PNG image; give a path ending in .png")
    assert not (tmp_path / "sheet.jpg").exists()
    with pytest.raises(RispError, match=r"--eps 2 is a step of 2× each ψ's range; use at most 0.1"):
        verify_folder(VerifyConfig(folder=str(tmp_path), samples=2, eps=2.0, tol=1e-3, checksums=False, repair=False))


def test_render_choices_are_the_modules_own_and_listed_in_help():
    """The CLI's literal choices (kept so that --help does not import Mitsuba) are the names the job accepts."""
    from risp_data import cli as data_cli
    from risp_data.generate import EXECUTORS
    from risp_data.psi import DOMAINS
    from risp_data.render import JACOBIAN_PATHS
    from risp_data.shards.writer import FORMATS

    assert data_cli.EXECUTORS == EXECUTORS and data_cli.JACOBIAN_PATHS == JACOBIAN_PATHS and data_cli.DOMAINS == DOMAINS
    assert set(data_cli.FORMAT_CHOICES) == set(FORMATS) | {"both"}
    r = CliRunner().invoke(cli, ["render", "--help"])
    assert r.exit_code == 0
    help_text = " ".join(r.output.split())
    for listed in ("quadrotor|cube|hand|rod", "train|target", "wds|zarr|both", "local|ray", "fast|legacy"):
        assert listed in help_text, listed


def test_bad_name_with_the_default_folder(tmp_path, monkeypatch, capsys):
    """Without --out, a bad name is the only line: no 'output folder' announced, no shards/ made."""
    monkeypatch.chdir(tmp_path)
    _entry_point_error(["render", "--env", "cubee", "--n", "2"], capsys, "Invalid value for '--env': 'cubee' is not one of")
    assert not (tmp_path / "shards").exists()


def test_mismatched_and_foreign_folders_untouched(rendered, tmp_path):
    before = {p: (p.stat().st_mtime_ns, p.stat().st_size) for p in rendered.rglob("*") if p.is_file()}
    r = _ok(_render(rendered, n=5, shard_size=2))  # the same job again: nothing to render, nothing rewritten
    assert "5/5 samples" in r.output and "rendered 0" in r.output
    r = CliRunner().invoke(cli, ["render", *TINY[:2], "--res", "16", "--spp", "2", "--n", "5", "--shard-size", "2",
                                 "--out", str(rendered)])
    _error_line(r, "holds another job (resolution=8 (folder) vs 16 (requested)); give a new folder with --out")
    _error_line(_render(rendered, "--seed", "3", n=5), "seed=0 (folder) vs 3")
    _error_line(_render(rendered, n=6), "n=5 (folder) vs 6")
    _error_line(_render(rendered, "--domain", "target", n=5), "domain=")
    after = {p: (p.stat().st_mtime_ns, p.stat().st_size) for p in rendered.rglob("*") if p.is_file()}
    assert after == before
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    _error_line(_render(foreign), "not empty and has no manifest.json")
    assert os.listdir(foreign) == ["notes.txt"]


def test_unwritable_output(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    _error_line(_render(blocker), "exists and is not a folder")
    _error_line(_render(blocker / "sub"), "is not writable")
    assert blocker.read_text() == "x"


def test_corrupt_or_truncated_shard_on_read(tmp_path, rendered):
    import shutil

    out = tmp_path / "c"
    shutil.copytree(rendered, out)
    tar = out / "wds" / "shard-000001.tar"
    tar.write_bytes(tar.read_bytes()[:3000])
    with pytest.raises(Exception, match="shard-000001.tar"):
        list(iter_wds(str(out)))
    _error_line(CliRunner().invoke(cli, ["verify", str(out)]), "shard-000001.tar")
    os.unlink(out / "data.zarr" / "images" / "c" / "0" / "0" / "0" / "0")
    r = CliRunner().invoke(cli, ["inspect", str(out)])  # the summary names each damaged shard, then one error
    assert r.exit_code == 1 and r.output.strip().splitlines()[-1].startswith("Error: 2 damaged shard(s)"), r.output
    assert "DAMAGED    shard 0:" in r.output and "images/c/0/0/0/0 is missing" in r.output
    (out / "manifest.json").write_text("{not json")
    _error_line(CliRunner().invoke(cli, ["inspect", str(out)]), "corrupt manifest")


def test_no_usable_llvm_is_one_line(tmp_path):
    env = dict(os.environ, DRJIT_LIBLLVM_PATH=str(tmp_path / "missing" / "libLLVM.so.19"))
    out = tmp_path / "o"
    r = subprocess.run([sys.executable, "-m", "risp_data", "render", *TINY, "--n", "2", "--out", str(out)],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 1
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "DRJIT_LIBLLVM_PATH" in lines[0] and "does not exist" in lines[0], r.stderr
    assert not out.exists()


RAY_DRIVER = ("import sys, ray; ray.init(num_cpus=int(sys.argv[1]), include_dashboard=False); "
              "sys.argv = ['risp-data'] + sys.argv[2:]; from risp_data.cli import main; main()")


def _render_on_ray(out, ray_env, workers, cluster_cpus=2):
    """The render command in its own process with --executor ray, on a local cluster of ``cluster_cpus`` CPUs
    (started first, so the command finds it, whatever this machine has); a hang fails the test at the timeout
    instead of hanging the suite."""
    cmd = [sys.executable, "-c", RAY_DRIVER, str(cluster_cpus), "render", *TINY, "--n", "5", "--shard-size", "2",
           "--workers", str(workers), "--executor", "ray", "--out", str(out)]
    return subprocess.run(cmd, capture_output=True, text=True, env=ray_env, timeout=180)


def test_ray_executor_matches_local(rendered, tmp_path, ray_env):
    """Where Ray is installed (the dev install brings its core): the same samples as the local executor."""
    pytest.importorskip("ray")
    r = _render_on_ray(tmp_path / "ray", ray_env, workers=2)
    assert r.returncode == 0, r.stderr[-3000:]
    _assert_same(_samples(rendered), _samples(tmp_path / "ray"))


def test_a_ray_render_with_more_workers_than_cluster_cpus_finishes(rendered, tmp_path, ray_env):
    """--workers 8 on a 2-CPU cluster (3 shards): at most one actor per CPU starts. With
    one actor per shard the one Ray could not schedule was handed a shard by the ActorPool, which waited for it for
    ever (seen: the render stuck at 4 of 6 shards until killed)."""
    pytest.importorskip("ray")
    r = _render_on_ray(tmp_path / "ray8", ray_env, workers=8)
    assert r.returncode == 0, r.stderr[-3000:]
    assert load_manifest(str(tmp_path / "ray8"))["complete"]
    _assert_same(_samples(rendered), _samples(tmp_path / "ray8"))


def test_ray_executor_without_ray_is_one_line(tmp_path, monkeypatch):
    """Without the extra (ray not importable, whether installed here or not) the render stops before writing."""
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    out = tmp_path / "no-ray"
    r = _render(out, "--executor", "ray", n=2)
    _error_line(r, "pip install 'risp[ray]'")
    assert not out.exists()


def test_image_size_counts_the_domains_samples_per_pass():
    """The target domain renders 4× --spp: 8192² pixels × 16 spp is 2^30 samples in the train domain but 2^32 in
    the target domain, beyond Mitsuba's uint32 sample counter (one check for render and make-video)."""
    from risp_data.errors import RispError
    from risp_data.generate import check_image_size

    check_image_size(8192, 16, "train")
    with pytest.raises(RispError, match=r"--res 8192 with --spp 16 needs 4,294,967,296 samples per pass in the target"):
        check_image_size(8192, 16, "target")
    with pytest.raises(RispError, match=r"--resolution 9000 is larger than the supported 8192 pixels"):
        check_image_size(9000, 1, "train", "--resolution")


def test_an_in_process_render_sets_drjit_threads_and_keeps_the_callers_torch_threads(tmp_path, monkeypatch):
    """workers=1 renders in this process: Dr.Jit's threads are set to the CPUs it may use (here made 1), not left to
    Dr.Jit's default of the machine's cores; torch runs one thread meanwhile, and both of the caller's counts come
    back (a table run that renders a test set in process between its one-thread cells had them changed)."""
    import drjit as dr
    import torch

    import risp_data.generate as gen
    from risp_data.generate import RenderJob, run_job

    before_dr, before_torch = dr.thread_count(), torch.get_num_threads()
    monkeypatch.setattr(gen, "available_cpus", lambda: 1)
    torch.set_num_threads(2)
    dr.set_thread_count(2)  # a count the render must change (the old code left Dr.Jit's as it found it)
    try:
        job = RenderJob(env="cube", n=2, out=str(tmp_path / "c"), resolution=8, spp=1, seed=0, shard_size=2, workers=1)
        seen = []
        real = gen.render_shard
        monkeypatch.setattr(gen, "render_shard", lambda *a, **k: (seen.append((dr.thread_count(),
                                                                                torch.get_num_threads())),
                                                                   real(*a, **k))[1])
        run_job(job, progress=False, log=lambda *_: None)
        assert seen and all(s == (1, 1) for s in seen), seen
        assert dr.thread_count() == 2 and torch.get_num_threads() == 2
    finally:
        dr.set_thread_count(before_dr)
        torch.set_num_threads(before_torch)


@pytest.mark.parametrize("damage", ["delete-array-metadata", "invalid-array-metadata", "garbage-root", "delete-store"])
def test_a_damaged_zarr_store_is_made_anew_and_rendered_again(rendered, tmp_path, damage):
    """A deleted, hand-edited or garbled data.zarr metadata file left the folder stuck ('damaged although shards are
    complete', also for verify --repair), reported complete though unreadable, or a JSONDecodeError traceback."""
    import json
    import shutil

    out = tmp_path / "cube"
    shutil.copytree(rendered, out)
    store = out / "data.zarr"
    if damage == "delete-array-metadata":
        (store / "images" / "zarr.json").unlink()
    elif damage == "invalid-array-metadata":
        (store / "psi" / "zarr.json").write_text(json.dumps({"zarr_format": 3}))
    elif damage == "garbage-root":
        (store / "zarr.json").write_text("garbage")
    else:
        shutil.rmtree(store)
    if damage != "delete-store":  # reading it: one line naming the store and the repair command
        _error_line(CliRunner().invoke(cli, ["inspect", str(out), "--png", str(tmp_path / "c.png")]), "corrupt zarr")
    _ok(_render(out, n=5))
    _assert_same(_samples(out), _samples(rendered))  # both readers, the same samples as the undamaged folder
    _ok(CliRunner().invoke(cli, ["inspect", str(out), "--png", str(tmp_path / "c.png")]))


@pytest.mark.parametrize("trouble", [PermissionError(13, "Permission denied"), OSError(24, "Too many open files")])
def test_a_zarr_store_that_cannot_be_read_now_is_left_alone(rendered, tmp_path, monkeypatch, trouble):
    """An error of the machine (permissions, file handles) while reading the store's metadata on resume is not a
    damaged store: one line, and every finished shard stays (it used to be taken for damage: every shard's files
    deleted and rendered again). A codec this zarr does not know is said as such, also without deleting."""
    import shutil

    import zarr

    out = tmp_path / "cube"
    shutil.copytree(rendered, out)
    def files():
        return sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file() and p.name != ".lock")

    before = files()
    assert len(list(out.glob("wds/*.tar"))) == 3 and len(list(out.glob("complete/*.json"))) == 3

    def refuse(*args, **kwargs):
        raise trouble

    monkeypatch.setattr(zarr, "open_group", refuse)
    _error_line(_render(out, n=5), "the store was left as it is")
    assert files() == before

    def unknown(*args, **kwargs):
        raise zarr.errors.UnknownCodecError("codec 'zstd-x' not available")

    monkeypatch.setattr(zarr, "open_group", unknown)
    _error_line(_render(out, n=5), "cannot read it; the store was left as it is")
    assert files() == before
    monkeypatch.undo()
    _assert_same(_samples(out), _samples(rendered))


def test_a_marker_left_by_hand_is_ignored_and_its_shard_rendered(rendered, tmp_path):
    import json
    import shutil

    out = tmp_path / "cube"
    shutil.copytree(rendered, out)
    m = json.load(open(out / "manifest.json"))
    m["shards"] = [r for r in m["shards"] if r["index"] != 2]
    (out / "manifest.json").write_text(json.dumps(m))
    (out / "complete" / "shard-000002.json").write_text(json.dumps({"index": 2, "start": 4, "stop": 5, "files": []}))
    _ok(_render(out, n=5))  # was an AttributeError traceback ('list' object has no attribute 'items')
    _assert_same(_samples(out), _samples(rendered))


@pytest.mark.parametrize("args, words", [
    (["--n", str(10 ** 20)], "is more than the 1,000,000,000 samples one data set may hold"),  # looped for minutes
    (["--n", "2", "--shard-size", str(10 ** 20)], "is larger than --n 2"),  # zarr allocated the whole shard
])
def test_sizes_beyond_any_data_set_are_refused_before_the_folder(tmp_path, args, words):
    out = tmp_path / "big"
    res = CliRunner().invoke(cli, ["render", *TINY, "--out", str(out), *args])
    _error_line(res, words)
    assert not out.exists()


@pytest.mark.parametrize("edit, words", [
    (lambda m: m.pop("counts"), None),  # inspect derives the counts from the shard records (was a KeyError)
    (lambda m: m["psi"].update(names="abc"), "field psi.names is not a list of names"),
    (lambda m: m["psi"].update(nominal=m["psi"]["nominal"][:-1]), "field psi.nominal is not a list of 8 finite"),
    (lambda m: m["psi"].update(high=["x"] * 8), "field psi.high is not a list of 8 finite numbers"),
    (lambda m: m.update(state_names=[1, 2]), "field state_names is not a list of names"),
    (lambda m: m.update(versions=[1]), "field versions is not an object"),
    (lambda m: m.update(resolution=10 ** 30), "field resolution"),
    (lambda m: m["shards"][0].update(files="abc"), "a record of field shards is malformed"),
    (lambda m: m["shards"][0].update(start=-2), "a record of field shards is malformed"),
    (lambda m: m["shards"][0].update(stop=10 ** 15), "a record of field shards is malformed"),
])
def test_a_hand_edited_manifest_is_one_line_for_inspect(rendered, tmp_path, edit, words):
    import json
    import shutil

    out = tmp_path / "cube"
    shutil.copytree(rendered, out)
    m = json.load(open(out / "manifest.json"))
    edit(m)
    (out / "manifest.json").write_text(json.dumps(m))
    res = CliRunner().invoke(cli, ["inspect", str(out), "--png", str(tmp_path / "c.png")])
    if words is None:
        _ok(res)
    else:
        _error_line(res, "corrupt manifest")
        assert words in res.output, res.output


def test_a_contact_sheet_under_a_file_names_the_file(rendered, tmp_path):
    (tmp_path / "afile").write_text("x")
    res = CliRunner().invoke(cli, ["inspect", str(rendered), "--png", str(tmp_path / "afile" / "x.png")])
    _error_line(res, "afile is a file, not a folder")


def test_a_missing_dependency_is_one_line():
    from risp_data.cli_util import user_error_line

    line = user_error_line(ImportError("No module named 'zarr'", name="zarr"))
    assert "the library 'zarr' cannot be imported" in line and "scripts/setup.sh" in line
    assert user_error_line(ImportError("bug", name="risp_train.nosuch")) is None  # risp's own: a bug, traceback
    assert "--batch-size" not in user_error_line(MemoryError()).split("(")[0]


def test_an_empty_out_is_named():
    res = CliRunner().invoke(cli, ["render", *TINY, "--n", "2", "--out", ""])
    _error_line(res, "--out is empty")  # was "output folder  is not writable: No such file or directory"
