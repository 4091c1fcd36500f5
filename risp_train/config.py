"""Training configuration: plain values in a frozen dataclass, and the two presets.

``paper`` follows the RISP paper: ResNet-18 (width 64), Adam with lr 1e-2 and weight decay 1e-6, cosine
decay to zero over all steps, batch 16, 100 epochs.  ``cpu`` is for this 2-core, GPU-less machine: the
same topology at width 16 (≈ 1/16 of the multiply-adds), 20 epochs, lr 3e-3 (the narrower network
diverged less often at a smaller step in our runs), everything else as in ``paper``.  Options given on
the command line override the preset.  γ defaults to the paper's per-environment value times the preset's
``GAMMA_SCALE``: 1 for ``paper``; 1/400 for ``cpu``, because with our input/target normalization the
regularizer starts at ‖M‖_F ≈ 1.8 against a state error ≈ 0.9 and the paper's cube γ = 20 (even γ = 1)
collapsed small runs to the mean predictor, while γ = 0.05 = 20/400 trained normally (docs/training.md).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace

from risp_data.errors import RispError

from .regularizers import REGULARIZERS

GAMMA_DEFAULTS = {"quadrotor": 1.0, "cube": 20.0, "hand": 100.0, "rod": 30.0}  # paper, per environment
GAMMA_SCALE = {"paper": 1.0, "cpu": 1.0 / 400.0}  # default γ = GAMMA_DEFAULTS[env] · GAMMA_SCALE[preset]

PRESETS: dict[str, dict] = {
    "paper": dict(epochs=100, batch_size=16, lr=1e-2, weight_decay=1e-6, width=64),
    "cpu": dict(epochs=20, batch_size=16, lr=3e-3, weight_decay=1e-6, width=16),
}


@dataclass(frozen=True)
class TrainConfig:
    shards: str  # training shard folder (manifest.json inside)
    out: str  # run folder
    reg: str = "none"  # none | surrogate | exact | stochastic
    gamma: float | None = None  # final regularizer weight; None → GAMMA_DEFAULTS[env] · GAMMA_SCALE[preset]
    gamma_ramp: float = 0.5  # γ ramps linearly from 0 over this fraction of all steps
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
    stem: str = "auto"  # auto | imagenet | small
    format: str = "auto"  # auto | wds | zarr
    shuffle_buffer: int = 256  # samples held by each worker's shuffle buffer
    stats_samples: int = 256  # samples streamed for the normalization statistics
    checkpoint_every: int = 0  # also checkpoint every N optimizer steps (0: only at epoch ends)
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


# fields that must agree for --resume to continue the same run
RESUME_FIELDS = ("reg", "gamma", "gamma_ramp", "epochs", "batch_size", "lr", "weight_decay", "seed", "width",
                 "blocks", "stem", "format", "shuffle_buffer", "stats_samples")


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
    if not cfg.lr > 0:
        raise RispError(f"--lr must be > 0, got {cfg.lr}")
    if cfg.gamma is not None and not cfg.gamma >= 0:
        raise RispError(f"--gamma must be >= 0, got {cfg.gamma}")
    if not 0 <= cfg.gamma_ramp <= 1:
        raise RispError(f"--gamma-ramp must be in [0, 1], got {cfg.gamma_ramp}")
    if cfg.workers < 0 or cfg.checkpoint_every < 0 or cfg.threads < 0:
        raise RispError("--workers, --threads and --checkpoint-every must be >= 0")
    if cfg.stem not in ("auto", "imagenet", "small"):
        raise RispError(f"unknown stem {cfg.stem!r}; choose auto, imagenet or small")


def resolved_gamma(cfg: TrainConfig, env: str) -> float:
    if cfg.reg == "none":
        return 0.0
    if cfg.gamma is not None:
        return float(cfg.gamma)
    return float(GAMMA_DEFAULTS[env] * GAMMA_SCALE.get(cfg.preset, 1.0))


def with_(cfg: TrainConfig, **kw) -> TrainConfig:
    return replace(cfg, **kw)
