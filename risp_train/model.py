"""The state predictor N: a ResNet-18 with exact instance normalization and SiLU activations.

Topology (He et al. 2016, "ResNet-18"): a stem, four stages of two basic blocks each (widths w, 2w, 4w,
8w; stages 2–4 start with a stride-2 block whose shortcut is a 1×1 stride-2 convolution), global
average pooling and one linear layer to the target dimension T.  As in RISP every normalization is an
instance normalization without affine parameters (:mod:`risp_train.norms`) and every activation is
SiLU (Swish).  Three stems, which divide the image side by 4, 2 and 1; the stages divide it by 8 more:

* ``imagenet``: 7×7 stride-2 convolution + 3×3 stride-2 max-pool (the original; 128×128 → 32×32);
* ``stride2``: one 3×3 stride-2 convolution (64×64 → 32×32);
* ``small``: one 3×3 stride-1 convolution (no down-sampling).

:func:`stem_for_resolution` picks the coarsest stem whose last stage still sees at least 4×4 pixels.  Why:
every block ends in an instance norm, which removes each channel's mean and scale over the map; on a 2×2 map
(the ``imagenet`` stem at 64×64) that leaves each channel 2 numbers of position and shape, and on a 1×1 map
nothing (the network refuses it).  At 64×64 the ``stride2`` stem's 4×4 last stage read the quadrotor's position
with 44 % less error on target-domain images than the ``imagenet`` stem's 2×2 (docs/RESULTS.md §The last
stage's map), at 1.8× the convolutions' cost.

The network maps *normalized* images (B, 3, H, W) to *normalized* targets (B, T); see
:mod:`risp_train.normalization` for both maps and :mod:`risp_train.predictor` for the raw-image wrapper.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from .norms import InstanceNorm


@dataclass(frozen=True)
class ModelConfig:
    out_dim: int  # T, the target dimension
    width: int = 64  # channels of the first stage (ResNet-18: 64)
    blocks: tuple[int, int, int, int] = (2, 2, 2, 2)  # basic blocks per stage (ResNet-18)
    stem: str = "imagenet"  # "imagenet" | "stride2" | "small"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["blocks"] = list(self.blocks)
        return d

    @staticmethod
    def from_dict(d: dict) -> "ModelConfig":
        return ModelConfig(
            out_dim=int(d["out_dim"]), width=int(d["width"]), blocks=tuple(int(b) for b in d["blocks"]),
            stem=str(d["stem"]),
        )


#: Each stem's down-sampling factor; the four stages divide by 8 more (strides 1, 2, 2, 2).
STEM_FACTOR = {"imagenet": 4, "stride2": 2, "small": 1}
STAGES_FACTOR = 8
MIN_LAST_MAP = 4  # pixels a side of the last stage's map that the automatic stem keeps (module docstring)


def min_resolution(stem: str) -> int:
    """The smallest image side the network takes with ``stem``: every stride-2 step maps n to ceil(n / 2), so
    the last stage is ceil(n / (stem factor · 8)) pixels a side, and it must be more than 1 (a 1×1 map is
    identically zero after instance norm)."""
    return STEM_FACTOR[stem] * STAGES_FACTOR + 1


def stem_for_resolution(resolution: int) -> str:
    """The coarsest stem whose last stage sees ≥ MIN_LAST_MAP² pixels: ``imagenet`` from 128 pixels, ``stride2``
    from 64, ``small`` below (the module docstring says why)."""
    for stem in ("imagenet", "stride2"):
        if resolution // (STEM_FACTOR[stem] * STAGES_FACTOR) >= MIN_LAST_MAP:
            return stem
    return "small"


def _conv3x3(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    # no bias: the following instance norm removes any per-channel constant
    return nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False)


class BasicBlock(nn.Module):
    """y = SiLU(IN(conv(SiLU(IN(conv(x))))) + shortcut(x)), shortcut = IN(conv1×1(x)) when the shape changes."""

    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.conv1 = _conv3x3(cin, cout, stride)
        self.norm1 = InstanceNorm()
        self.conv2 = _conv3x3(cout, cout)
        self.norm2 = InstanceNorm()
        self.act = nn.SiLU()
        self.shortcut: nn.Module = nn.Identity()
        if stride != 1 or cin != cout:
            self.shortcut = nn.Sequential(nn.Conv2d(cin, cout, 1, stride=stride, bias=False), InstanceNorm())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.act(self.norm1(self.conv1(x)))
        h = self.norm2(self.conv2(h))
        return self.act(h + self.shortcut(x))


class ResNet18(nn.Module):
    """N: normalized image (B, 3, H, W) → normalized target (B, T)."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        w = config.width
        if config.stem == "imagenet":
            self.stem = nn.Sequential(
                nn.Conv2d(3, w, 7, stride=2, padding=3, bias=False), InstanceNorm(), nn.SiLU(),
                nn.MaxPool2d(3, stride=2, padding=1),
            )
        elif config.stem == "stride2":
            self.stem = nn.Sequential(nn.Conv2d(3, w, 3, stride=2, padding=1, bias=False), InstanceNorm(), nn.SiLU())
        elif config.stem == "small":
            self.stem = nn.Sequential(_conv3x3(3, w), InstanceNorm(), nn.SiLU())
        else:
            raise ValueError(f"unknown stem {config.stem!r}")
        stages = []
        cin = w
        for i, n in enumerate(config.blocks):
            cout = w * 2**i
            blocks = [BasicBlock(cin, cout, 1 if i == 0 else 2)]
            blocks += [BasicBlock(cout, cout, 1) for _ in range(n - 1)]
            stages.append(nn.Sequential(*blocks))
            cin = cout
        self.stages = nn.Sequential(*stages)
        self.head = nn.Linear(cin, config.out_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.stages(self.stem(as_nchw(x)))  # (B, 8w, h, w)
        if h.shape[-1] * h.shape[-2] == 1:
            raise ValueError(f"input {tuple(x.shape[-2:])} is too small for stem {self.config.stem!r}: "
                             "the last stage is 1×1, where instance norm is identically zero")
        return self.head(h.mean(dim=(-2, -1)))  # global average pool → (B, 8w) → (B, T)


def as_nchw(x: torch.Tensor) -> torch.Tensor:
    """``x`` in the plain NCHW memory layout, whatever strides it arrived with.

    Why: an image batch permuted from (B, H, W, 3) is channels-last in memory, and PyTorch then runs every
    convolution through oneDNN's NHWC kernels.  oneDNN's 1×1 stride-2 backward-weights kernel with fewer
    input channels than its register block (8 on AVX2, 16 on AVX-512) writes past its workspace
    (uxlfoundation/oneDNN#6035): a ResNet of width < 8 — or < 16 on AVX-512 — hung training for good,
    crashed it, or silently corrupted its gradients.  The NCHW path does not have the bug.
    """
    return x.contiguous(memory_format=torch.contiguous_format)


def build_model(config: ModelConfig, seed: int) -> ResNet18:
    """A freshly initialised network; the initial weights depend only on ``seed``."""
    devnull = torch.random.fork_rng(devices=[])
    with devnull:  # never touch the caller's global RNG
        torch.manual_seed(seed)
        return ResNet18(config)
