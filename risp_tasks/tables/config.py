"""Table configuration: plain values in a frozen dataclass; the ``cpu``/``paper`` presets and ``--quick``."""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field, replace

from risp_data.envs import ENV_NAMES
from risp_data.errors import RispError

from . import TABLES

EXTRA_TABLES: tuple[str, ...] = ("regularizers", "sampling")  # the project's own: not among the paper's four
from .methods import METHODS

#: Sizes per preset.  ``cpu``: this 2-core machine, sized so that the four tables fit in 4 hours with ``--jobs 2``
#: (docs/tables.md: an image-loss iteration costs 0.25-0.45 s per 64x64 image on one core); ``paper``: the paper's scale,
#: for a GPU machine (``cuda_ad_rgb`` renders, CUDA torch).  ``--quick`` shrinks everything to a smoke run.
PRESETS: dict[str, dict] = {
    "cpu": dict(n_train=1000, n_test=16, resolution=64, spp=8, frames=8, iterations=40, train_preset="cpu"),
    "paper": dict(n_train=10000, n_test=200, resolution=64, spp=16, frames=10, iterations=100, train_preset="paper"),
}
#: Where the control table's optimising methods start: ``neutral`` (x = 0, the `average` row's actions, so each
#: method's row shows what its loss adds to the same start) or ``random`` (the seeded draw, as the other tasks).
CONTROL_STARTS: tuple[str, ...] = ("neutral", "random")
QUICK: dict = dict(n_train=32, n_test=4, spp=4, frames=3, iterations=3, epochs=1, width=8)
#: Repeat k under ``--seed s`` is seeded s·REPEAT_STRIDE + k (its test images and video: TEST_SEED + that; its
#: random guess; the regularizer table's training seed), so that two seeds never share a repeat's data or guess
#: (with ``s + k`` the repeats of --seed 1 were those of --seed 0 shifted by one); --seed 0 keeps k.
REPEAT_STRIDE = 1000


def repeat_seed(seed: int, repeat: int) -> int:
    """The seed of repeat ``repeat`` of a table run with ``--seed seed`` (REPEAT_STRIDE)."""
    return seed * REPEAT_STRIDE + repeat


@dataclass(frozen=True)
class TableConfig:
    table: str
    out: str = "tables"
    preset: str = "cpu"
    repeats: int = 4
    envs: tuple[str, ...] = ENV_NAMES
    methods: tuple[str, ...] = METHODS
    seed: int = 0
    n_train: int = 1000  # training-domain samples (with Jacobians) per environment
    n_test: int = 16  # target-domain test images per repeat (estimation)
    resolution: int = 64
    spp: int = 8
    frames: int = 8  # reference-video frames (sysid, imitation; control: horizon)
    iterations: int = 40  # optimisation iterations of the optimising methods
    control_start: str = "neutral"  # control: the optimisers' initial actions, neutral (x = 0) | random (seeded)
    residual: str = "l2"  # the task tables' residual norm in N's space (render/state/oracle losses): l2 (the paper's) | l1
    lr: float = 1e-2  # RMSProp step of the per-image state optimisation (estimation: pixelwise, perceptual)
    epochs: int | None = None  # training epochs (None: the risp-train preset's)
    width: int | None = None  # network width (None: the risp-train preset's)
    batch_size: int | None = None  # training batch (None: the risp-train preset's)
    reg: str = field(default_factory=lambda: default_reg())  # the regularizer of `ours`; `ours-no-grad`: none
    train_preset: str = "cpu"  # risp-train preset of both networks
    perceptual_weights: str | None = None  # local feature-extractor weights (methods.FeatureExtractor)
    workers: int = 1  # data workers of training
    executor: str = "local"  # local | ray
    jobs: int = 1  # local executor: cells computed at once, one process each (0: one per available CPU; the CLI's default)
    quick: bool = False
    progress: bool = True

    def to_dict(self) -> dict:
        d = asdict(self)
        d["envs"], d["methods"] = list(self.envs), list(self.methods)
        return d


def make_config(table: str, preset: str = "cpu", quick: bool = False, **overrides) -> TableConfig:
    """Preset sizes, then ``--quick``'s, then every override that is not None; validated."""
    if table not in TABLES + EXTRA_TABLES:
        raise RispError(f"unknown table {table!r}; choose one of: {', '.join(TABLES + EXTRA_TABLES)}")
    if preset not in PRESETS:
        raise RispError(f"unknown preset {preset!r}; choose one of: {', '.join(PRESETS)}")
    values = dict(PRESETS[preset])
    if quick:
        values.update(QUICK)
    values.update({k: v for k, v in overrides.items() if v is not None})
    values.setdefault("reg", default_reg())
    if table == "regularizers" and overrides.get("methods") is None:
        from risp_train.regularizers import REGULARIZERS

        values["methods"] = REGULARIZERS  # the rows of this table are the regularizers
    if table == "sampling":
        from .sampling import SCHEMES

        values.setdefault("envs", ("rod",))
        if overrides.get("methods") is None:
            values["methods"] = SCHEMES  # the rows: temporal-sampling schemes
    cfg = TableConfig(table=table, preset=preset, quick=quick, **values)
    validate(cfg)
    return cfg


def default_reg() -> str:
    """The regularizer of `ours`: risp-train's default (``risp-train fit``'s ``DEFAULT_REG``, the calibrated
    one of docs/training.md) when it is not ``none``, else the paper's surrogate (Eq. 12) — so the tables
    follow the trainer's choice."""
    from risp_train.config import DEFAULT_REG

    return DEFAULT_REG if DEFAULT_REG != "none" else "surrogate"


def validate(cfg: TableConfig) -> None:
    from risp_train.regularizers import REGULARIZERS

    for option, values in (("--envs", cfg.envs), ("--methods", cfg.methods)):
        if not values:
            raise RispError(f"{option} is empty: name at least one")
        if len(set(values)) != len(values):  # the cells would run twice and the rows repeat
            raise RispError(f"{option} names an entry twice: {','.join(values)}")
    for env in cfg.envs:
        if env not in ENV_NAMES:
            raise RispError(f"unknown environment {env!r}; choose from: {', '.join(ENV_NAMES)}")
    others = [env for env in cfg.envs if env != "rod"]
    if cfg.table == "sampling" and others:  # every cell would be N/A: refused before a folder is made
        raise RispError(f"--table sampling is the rod's temporal-sampling ablation (the paper's): --envs rod, "
                        f"not {','.join(others)}")
    from .sampling import SCHEMES

    rows, what = {"regularizers": (REGULARIZERS, "regularizer"), "sampling": (SCHEMES, "sampling scheme")}.get(
        cfg.table, (METHODS, "method"))
    for m in cfg.methods:
        if m not in rows:
            raise RispError(f"unknown {what} {m!r}; choose from: {', '.join(rows)}")
    if cfg.reg not in REGULARIZERS or cfg.reg == "none":
        raise RispError(f"the regularizer of `ours` must be one of: {', '.join(r for r in REGULARIZERS if r != 'none')}")
    for name in ("repeats", "n_train", "n_test", "resolution", "spp", "frames"):
        if getattr(cfg, name) < 1:
            raise RispError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(cfg, name)}")
    if cfg.repeats > REPEAT_STRIDE:
        raise RispError(f"--repeats must be <= {REPEAT_STRIDE} (each seed's repeats have their own seeds), "
                        f"got {cfg.repeats}")
    if cfg.iterations < 0:
        raise RispError(f"--iterations must be >= 0, got {cfg.iterations}")
    if not cfg.lr > 0:
        raise RispError(f"the table's lr must be > 0, got {cfg.lr}")
    if cfg.perceptual_weights and not os.path.isfile(cfg.perceptual_weights):  # before any cell is computed
        raise RispError(f"{cfg.perceptual_weights}: perceptual weights file not found")
    from risp_tasks.tasks.config import RESIDUALS

    if cfg.residual not in RESIDUALS:
        raise RispError(f"unknown residual {cfg.residual!r}; choose one of: {', '.join(RESIDUALS)}")
    if cfg.control_start not in CONTROL_STARTS:
        raise RispError(f"unknown control start {cfg.control_start!r}; choose one of: {', '.join(CONTROL_STARTS)}")
    if cfg.seed < 0:
        raise RispError(f"--seed must be >= 0, got {cfg.seed}")
    if cfg.jobs < 0:
        raise RispError(f"--jobs must be >= 0 (0: one per available CPU), got {cfg.jobs}")
    if cfg.executor not in ("local", "ray"):
        raise RispError(f"unknown executor {cfg.executor!r}; choose local or ray")


def with_(cfg: TableConfig, **kw) -> TableConfig:
    return replace(cfg, **kw)
