"""Video -> diagnosis (issue 10, item 6): a target-domain quadrotor video (30 fps, 10 s) with a hidden constant
wind and its known commands; `estimate` turns it into a measured-data trajectory and `diagnose` reads it.

* ``test_pipeline_runs`` (slow): the whole chain on a tiny network — the files fit together and diagnose
  answers; its verdict is not asserted (a one-epoch 16×16 network's estimates are noise).
* ``test_names_wind_with_a_trained_network`` (slow): the acceptance test.  It needs a trained quadrotor network
  (set RISP_TASK_QUADROTOR_MODEL to its model.pt); without one it is skipped.  It is not given a briefly trained
  fixture network: the same pipeline with the demo network (400 images; 17.7° attitude error on this video, while
  the 3 N wind is worth a 5.8° tilt) answered `unexplained` with a wind fit pointing along −y, and a 10000-image
  `stride2` network (6.4°) with a wind fit along +x that is not yet significant (ΔBIC −7.4) — a network that fits
  a CI budget cannot pass it honestly (docs/RESULTS.md §Video → diagnosis has the measurements; there the
  effect-free half gives `none` with a 10000-image network).
"""

import json
import os

import pytest

from tasks_helpers import shared_model

pytest.importorskip("av")
pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800)]


def _video_to_report(tmp_path, model, effect, resolution, seed=7):
    from risp_tasks.diagnose.run import DiagnoseConfig, diagnose
    from risp_tasks.tasks.config import TaskConfig
    from risp_tasks.tasks.reference import ReferenceConfig, make_reference
    from risp_tasks.tasks.run import run_task

    video = str(tmp_path / "flight.mp4")
    make_reference(ReferenceConfig(env="quadrotor", out=video, frames=300, fps=30, resolution=resolution, spp=4,
                                   effect=effect, seed=seed, progress=False))
    run_task(TaskConfig(task="estimate", video=video, model=model, actions=str(tmp_path / "flight.actions.csv"),
                        out=str(tmp_path / "est"), progress=False, plots=False), echo=lambda s: None)
    return diagnose(DiagnoseConfig(data=(str(tmp_path / "est" / "trajectory.csv"),), env="quadrotor",
                                   out=str(tmp_path / "report"), seed=0, plots=False, progress=False))


def test_pipeline_runs(tmp_path_factory, tmp_path):
    report = _video_to_report(tmp_path, shared_model(tmp_path_factory, "quadrotor"), "wind:3,0,0", 16)
    assert isinstance(report["cause"], str) and report["reason"]
    # diagnose read estimate's trajectory: one sample per frame of the 10 s, 30 fps video
    assert report["data"]["samples"] == 300, report["data"]
    if report["cause"] == "unexplained":  # on a network's estimates the verdict names their noise
        assert "estimate noise" in report["reason"], report["reason"]
    assert os.path.isfile(tmp_path / "report" / "report.json")
    truth = json.load(open(tmp_path / "flight.truth.json"))
    assert truth["params"]["wind.fx"] == 3.0 and truth["fps"] == 30 and len(truth["env_states"]) == 300


@pytest.mark.skipif(not os.environ.get("RISP_TASK_QUADROTOR_MODEL"),
                    reason="needs a cpu-preset quadrotor network: set RISP_TASK_QUADROTOR_MODEL=path/to/model.pt")
def test_names_wind_with_a_trained_network(tmp_path):
    model = os.environ["RISP_TASK_QUADROTOR_MODEL"]
    import risp_train

    resolution = risp_train.load(model).resolution
    report = _video_to_report(tmp_path / "wind", model, "wind:3,0,0", resolution)
    assert report["cause"] == "wind", report["reason"]
    fx, fy = (report["parameters"][k]["value"] for k in ("wind.fx", "wind.fy"))
    assert fx > 0 and abs(fx) > abs(fy)
    clean = _video_to_report(tmp_path / "clean", model, None, resolution)
    assert clean["cause"] in ("none", "unexplained"), clean
    if clean["cause"] == "unexplained":  # "noise floor" alone would not do: the estimates must be named
        assert "estimate noise" in clean["reason"], clean["reason"]
