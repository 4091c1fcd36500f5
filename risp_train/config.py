"""Training configuration: plain values in a frozen dataclass, and the two presets.

``paper`` follows the RISP paper: ResNet-18 (width 64), Adam with lr 1e-2 and weight decay 1e-6, cosine
decay to zero over all steps, batch 16, 100 epochs.  ``cpu`` is for this 2-core, GPU-less machine: the
same topology at width 16 (≈ 1/16 of the multiply-adds), 20 epochs, lr 3e-3 (the narrower network
diverged less often at a smaller step in our runs), everything else as in ``paper``.  Options given on
the command line override the preset; ``default_preset()`` is ``paper`` where torch sees a CUDA GPU and
``cpu`` elsewhere.

γ is dimensionless: it weighs the calibrated rendering-induced error R against the state error
(risp_train/regularizers.py, §One scale), so no factor depends on the preset.  The paper's γ values (quadrotor
1, cube 20, hand 100, rod 30) belong to its own normalization and do not carry over; the defaults below
were chosen by the sweep in docs/training.md §Calibrated regularizer (per environment, several seeds).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

from risp_data.errors import RispError

from .defaults import DEFAULT_REG  # re-exported here (risp_train.config.DEFAULT_REG)
from .model import STEM_FACTOR
from .regularizers import REGULARIZERS

# dimensionless; docs/training.md §Sweep of γ.  hand 0.05: at 5000 samples γ = 0.3 cost the hand 11 % against `none`
# and 0.05 gained 3 % (3 seeds).  quadrotor and cube start at half the run (GAMMA_START_DEFAULTS).
GAMMA_DEFAULTS = {"quadrotor": 0.3, "cube": 0.3, "hand": 0.05, "rod": 0.3}
# the fraction of the steps before γ's ramp starts (docs/training.md §γ schedule); 0 where not listed.  cube 0.5:
# ramped in from the first step, the regularizer kept the cube's attitude from being learned at every γ tried
# (123° against 76° for `none`, 10000 samples); started at half the run, 76° ± 11° and 11 % better position than
# `none`.  quadrotor 0.5: position −6 % and attitude −4 % against `none` (from the first step: −5 %, +8 %).  3 seeds
# each at 10000 samples (docs/RESULTS.md §The regularizer's late start); hand and rod were not tried late.
GAMMA_START_DEFAULTS = {"quadrotor": 0.5, "cube": 0.5}

PRESETS: dict[str, dict] = {
    "paper": dict(epochs=100, batch_size=16, lr=1e-2, weight_decay=1e-6, width=64),
    "cpu": dict(epochs=20, batch_size=16, lr=3e-3, weight_decay=1e-6, width=16),
}


@dataclass(frozen=True)
class TrainConfig:
    shards: str  # training shard folder (manifest.json inside)
    out: str  # run folder
    reg: str = "none"  # none | surrogate | exact | stochastic (the CLI's default is DEFAULT_REG)
    gamma: float | None = None  # final regularizer weight (dimensionless); None → GAMMA_DEFAULTS[env]
    gamma_ramp: float = 0.5  # γ ramps linearly from 0 over this fraction of the steps after its start
    gamma_start: float | None = None  # γ is 0 before this fraction of all steps, then ramps; None → per env
    epochs: int = 100
    batch_size: int = 16
    lr: float = 1e-2
    weight_decay: float = 1e-6
    seed: int = 0
    workers: int = 2  # DataLoader worker processes (per rank)
    threads: int = 0  # torch intra-op threads per rank (0: CPUs left after the workers; risp_data.threads)
    device: str = "auto"  # auto (CUDA when torch sees a GPU) | cpu | cuda | cuda:N
    width: int = 64  # ResNet-18 first-stage channels
    blocks: tuple[int, int, int, int] = (2, 2, 2, 2)
    stem: str = "auto"  # auto | imagenet | stride2 | small (auto: model.stem_for_resolution)
    format: str = "auto"  # auto | wds | zarr
    cache: str = "auto"  # auto | memory | stream: decode the data once into memory, or stream it (memory.py)
    shuffle_buffer: int = 256  # samples held by each worker's shuffle buffer
    stats_samples: int = 256  # samples streamed for the normalization statistics
    checkpoint_every: int = 0  # also checkpoint every N optimizer steps (0: only at epoch ends)
    rank_check: str = "stop"  # torchrun ranks whose weights differ at an epoch end: stop | resync (rank 0's state)
    val: str | None = None  # optional held-out shard folder, evaluated at each epoch end
    val_samples: int = 256
    preset: str = "paper"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["blocks"] = list(self.blocks)
        return d

    @staticmethod
    def from_dict(d: dict) -> "TrainConfig":
        known = {f.name for f in fields(TrainConfig)}
        kw = {k: v for k, v in d.items() if k in known}
        kw["blocks"] = tuple(int(b) for b in kw.get("blocks", (2, 2, 2, 2)))
        return TrainConfig(**kw)


RANK_CHECKS = ("stop", "resync")  # what a fit does when its ranks' weights differ (docs/training.md)

# fields that must agree for --resume to continue the same run
RESUME_FIELDS = ("reg", "gamma", "gamma_ramp", "gamma_start", "epochs", "batch_size", "lr", "weight_decay", "seed",
                 "width", "blocks", "stem", "format", "shuffle_buffer", "stats_samples")


def default_preset() -> str:
    """``paper`` where torch sees a CUDA GPU, else ``cpu`` (the preset a user without a GPU can live with)."""
    import torch

    return "paper" if torch.cuda.is_available() else "cpu"


def make_config(shards: str, out: str, preset: str = "paper", **overrides) -> TrainConfig:
    """Preset values, then every override that is not None; validates the plain values."""
    if preset not in PRESETS:
        raise RispError(f"unknown --preset {preset!r}; choose one of: {', '.join(PRESETS)}")
    values = dict(PRESETS[preset])
    values.update({k: v for k, v in overrides.items() if v is not None})
    cfg = TrainConfig(shards=shards, out=out, preset=preset, **values)
    validate(cfg)
    return cfg


def validate(cfg: TrainConfig) -> None:
    if cfg.reg not in REGULARIZERS:
        raise RispError(f"unknown --reg {cfg.reg!r}; choose one of: {', '.join(REGULARIZERS)}")
    for name in ("epochs", "batch_size", "width", "stats_samples"):
        if getattr(cfg, name) < 1:
            raise RispError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(cfg, name)}")
    if not 0 < cfg.lr < math.inf:
        raise RispError(f"--lr must be a finite number > 0, got {cfg.lr}")
    if not 0 <= cfg.weight_decay < math.inf:
        raise RispError(f"--weight-decay must be a finite number >= 0, got {cfg.weight_decay}")
    if cfg.gamma is not None and not cfg.gamma < math.inf:
        raise RispError(f"--gamma must be finite, got {cfg.gamma}")
    if cfg.gamma is not None and not cfg.gamma >= 0:
        raise RispError(f"--gamma must be >= 0, got {cfg.gamma}")
    if not 0 <= cfg.gamma_ramp <= 1:
        raise RispError(f"--gamma-ramp must be in [0, 1], got {cfg.gamma_ramp}")
    if cfg.gamma_start is not None and not 0 <= cfg.gamma_start < 1:
        raise RispError(f"--gamma-start must be in [0, 1), got {cfg.gamma_start}")
    if not 0 <= cfg.seed < 2**63:  # torch.manual_seed (the network's initialisation) takes a signed 64-bit integer
        raise RispError(f"--seed must be in [0, 2**63), got {cfg.seed}")
    if cfg.workers < 0 or cfg.checkpoint_every < 0 or cfg.threads < 0:
        raise RispError("--workers, --threads and --checkpoint-every must be >= 0")
    if cfg.rank_check not in RANK_CHECKS:
        raise RispError(f"unknown --rank-check {cfg.rank_check!r}; choose one of: {', '.join(RANK_CHECKS)}")
    if cfg.cache not in ("auto", "memory", "stream"):
        raise RispError(f"unknown --cache {cfg.cache!r}; choose one of: auto, memory, stream")
    if cfg.stem != "auto" and cfg.stem not in STEM_FACTOR:
        raise RispError(f"unknown stem {cfg.stem!r}; choose auto, {', '.join(STEM_FACTOR)}")


def resolved_gamma(cfg: TrainConfig, env: str) -> float:
    if cfg.reg == "none":
        return 0.0
    if cfg.gamma is not None:
        return float(cfg.gamma)
    if env not in GAMMA_DEFAULTS:  # a manifest naming no known environment: the registry's own line
        from risp_data.envs import get_environment

        get_environment(env)
    return float(GAMMA_DEFAULTS[env])


def resolved_gamma_start(cfg: TrainConfig, env: str) -> float:
    if cfg.gamma_start is not None:
        return float(cfg.gamma_start)
    return float(GAMMA_START_DEFAULTS.get(env, 0.0))


def with_(cfg: TrainConfig, **kw) -> TrainConfig:
    return replace(cfg, **kw)
