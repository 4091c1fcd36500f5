"""The README's main job, end to end: ``risp demo --quick`` renders, trains, evaluates and diagnoses."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest


@pytest.mark.slow
def test_quick_demo_runs_end_to_end(tmp_path):
    out = tmp_path / "demo"
    proc = subprocess.run(
        [sys.executable, "-m", "cli", "demo", "--quick", "--seed", "3", "--out", str(out)],
        capture_output=True, text=True, timeout=1500,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]

    meta = json.loads((out / "demo.json").read_text())
    assert meta["seed"] == 3
    # render+inspect per env and domain; train/val/target sets, fit, two evals, make-video, sysid, diagnose
    assert len(meta["commands"]) >= 4 * 2 * 2 + 9

    for env in ("quadrotor", "cube", "hand", "rod"):
        for domain in ("train", "target"):
            folder = out / "preview" / f"{env}-{domain}"
            manifest = json.loads((folder / "manifest.json").read_text())
            assert manifest["env"] == env and manifest["domain"] == domain
            assert (folder / "contact_sheet.png").stat().st_size > 1000

    run = out / "runs" / "quadrotor"
    assert (run / "model.pt").exists() and (run / "losses.png").exists()
    for name in ("val", "target"):
        ev = json.loads((run / f"eval-{name}.json").read_text())
        assert set(ev["results"]) >= {"model", "average", "random"}
        for method in ("model", "average", "random"):
            assert {"position", "attitude"} <= set(ev["groups"][method])
            assert ev["groups"][method]["position"]["mean"] > 0

    truth = json.loads((out / "video" / "quadrotor.truth.json").read_text())
    sysid = json.loads((out / "sysid" / "result.json").read_text())
    err = sysid["errors"]["parameter_error_final"]["mass"]
    assert err == pytest.approx(abs(sysid["estimates"]["parameters"]["mass"] - truth["params"]["mass"]))
    assert "System identification" in (out / "README.md").read_text()
    assert sysid["config"]["residual"] == "l1" and "residual `l1`" in (out / "README.md").read_text()

    report = json.loads((out / "diagnose" / "report.json").read_text())
    for key in ("cause", "parameters", "ranking", "base_error", "extended_error", "gain"):
        assert key in report
    assert report["seed"] == 3
    assert (out / "README.md").read_text().startswith("# risp demo")

    # run again into the same folder: the finished steps are reused (diagnose ran again before: minutes), the
    # results they wrote stay as they were
    kept = {p: p.stat().st_mtime_ns for p in (out / "diagnose" / "report.json", out / "sysid" / "result.json",
                                             run / "model.pt", out / "video" / "quadrotor.truth.json")}
    again = subprocess.run([sys.executable, "-m", "cli", "demo", "--quick", "--seed", "3", "--out", str(out)],
                           capture_output=True, text=True, timeout=1500)
    assert again.returncode == 0, again.stderr[-3000:]
    ran = [c["command"].split()[1] for c in json.loads((out / "demo.json").read_text())["commands"]]
    assert not {"diagnose", "sysid", "make-video"} & set(ran) and "fit" in ran, ran
    assert {p: p.stat().st_mtime_ns for p in kept} == kept


def test_risp_group_lists_the_three_tools_and_demo():
    proc = subprocess.run([sys.executable, "-m", "cli", "--help"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0
    for name in ("data", "train", "task", "demo"):
        assert f"  {name}" in proc.stdout


def test_unknown_environment_is_one_error_line_through_the_group():
    proc = subprocess.run(
        [sys.executable, "-m", "cli", "data", "render", "--env", "boat", "--n", "1", "--out", "unused"],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 1
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "boat" in lines[0] and "quadrotor" in lines[0]


def test_demo_refuses_a_file_as_output_folder(tmp_path):
    target = tmp_path / "a-file"
    target.write_text("keep me")
    proc = subprocess.run([sys.executable, "-m", "cli", "demo", "--quick", "--out", str(target)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0 and "is a file" in proc.stderr
    assert target.read_text() == "keep me"  # nothing already written is touched


def test_random_guess_error_is_the_mean_absolute_error_of_a_uniform_guess():
    import numpy as np

    from risp_tasks.demo import random_guess_error

    draws = np.random.default_rng(0).uniform(2.8, 3.2, 200_000)
    for truth in (2.8, 2.95, 3.1):
        assert random_guess_error(truth, 2.8, 3.2) == pytest.approx(np.abs(draws - truth).mean(), rel=1e-2)


def test_demo_refuses_a_folder_that_is_not_a_demos(tmp_path):
    """--out into a user's folder: one line, nothing written beside its files, even when its names are the demo's
    (a README.md, a shards/); a demo's own folder (marker or demo.json) is resumed, hidden files do not count."""
    from risp_tasks.demo import DEMO_MARKER, check_demo_folder

    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("keep me")
    proc = subprocess.run([sys.executable, "-m", "cli", "demo", "--quick", "--out", str(mine)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and "not a demo's (thesis.tex)" in proc.stderr
    assert sorted(p.name for p in mine.iterdir()) == ["thesis.tex"]
    project = tmp_path / "project"
    (project / "shards").mkdir(parents=True)
    (project / "README.md").write_text("my project")
    with pytest.raises(Exception, match=r"not a demo's \(README.md, shards\)"):
        check_demo_folder(project)
    interrupted = tmp_path / "interrupted"
    (interrupted / "preview").mkdir(parents=True)
    (interrupted / DEMO_MARKER).touch()
    (interrupted / ".tmp-k2j").mkdir()  # a hard-killed task's temporary
    check_demo_folder(interrupted)
    older = tmp_path / "older"
    (older / "shards").mkdir(parents=True)
    (older / "demo.json").write_text("{}")
    check_demo_folder(older)
    hidden = tmp_path / "hidden"
    hidden.mkdir()
    (hidden / ".DS_Store").write_text("")
    check_demo_folder(hidden)
    check_demo_folder(tmp_path / "new")


def test_demo_script_passes_options_and_refuses_an_option_as_folder(tmp_path):
    """`bash scripts/demo.sh --help` shows risp demo's help (it used to become `--out --help`: a folder named
    "--help", then a failed render); `risp demo --out --help` is refused before anything is written."""
    import hashlib

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    stamp = os.path.join(root, ".venv", ".risp-setup")  # demo.sh runs the set-up: only where it has nothing to do
    want = hashlib.sha256(open(os.path.join(root, "pyproject.toml"), "rb").read()).hexdigest() + " " + root
    if not os.path.isfile(stamp) or open(stamp).read().strip() != want:
        pytest.skip("scripts/setup.sh would install here (no matching .venv/.risp-setup): run it first")
    proc = subprocess.run(["bash", os.path.join(root, "scripts", "demo.sh"), "--help"], capture_output=True,
                          text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "--quick" in proc.stdout and "--seed" in proc.stdout
    assert not os.path.exists(os.path.join(root, "--help")) and not (tmp_path / "--help").exists()
    proc = subprocess.run([sys.executable, "-m", "cli", "demo", "--out", "--help"], capture_output=True, text=True,
                          timeout=120, cwd=root)
    assert proc.returncode == 1 and "--out --help looks like an option, not a folder" in proc.stderr, proc.stderr
    assert not os.path.exists(os.path.join(root, "--help"))
