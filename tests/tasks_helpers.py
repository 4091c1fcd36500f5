"""A tiny trained predictor per environment for the task tests: a handful of real renders (16×16, 2 spp) and
one short real training run (risp_train.fit), cached per test session."""

from __future__ import annotations

import subprocess
import sys

RES = 16


def tiny_model(root, env: str, n: int = 16) -> str:
    from risp_train.config import make_config
    from risp_train.train import fit

    shards = root / f"shards-{env}"
    cmd = [sys.executable, "-m", "risp_data", "render", "--env", env, "--n", str(n), "--res", str(RES), "--spp", "2",
           "--shard-size", str(n), "--seed", "0", "--workers", "1", "--quiet", "--out", str(shards)]
    subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=300)
    cfg = make_config(str(shards), str(root / "runs" / env), preset="cpu", epochs=1, batch_size=4, width=4, workers=0,
                      lr=3e-3, shuffle_buffer=8, stats_samples=n, reg="none")
    return str(fit(cfg, progress=False))


_CACHE: dict = {}


def shared_model(tmp_path_factory, env: str) -> str:
    """One tiny model per environment for the whole test session."""
    if env not in _CACHE:
        _CACHE[env] = tiny_model(tmp_path_factory.mktemp(f"tiny-{env}"), env)
    return _CACHE[env]


def shared_video(tmp_path_factory, env: str, frames: int = 6) -> str:
    """A small target-domain reference video (+ .truth.json, .actions.csv) per environment."""
    key = ("video", env, frames)
    if key not in _CACHE:
        from risp_tasks.tasks.reference import ReferenceConfig, make_reference

        out = str(tmp_path_factory.mktemp(f"video-{env}") / f"{env}.mp4")
        make_reference(ReferenceConfig(env=env, out=out, frames=frames, resolution=RES, spp=2, seed=3, progress=False))
        _CACHE[key] = out
    return _CACHE[key]
