"""Feature extractors F of the ``perceptual`` loss, L(θ) = mean_t ‖F(R(s_t(θ))) − F(I_t)‖² (docs/tasks.md §Losses).

Pretrained weights cannot be downloaded at run time: a local torchvision ``vgg16`` state dict gives
:class:`VGGBlock` (``--perceptual-weights``); without one the project's own :class:`FilterBank` is used.
Both are frozen and differentiable w.r.t. the images.  Used by the tasks (risp_tasks.tasks.loop) and the
tables (risp_tasks.tables).
"""

from __future__ import annotations

import os

import torch

from risp_data.errors import RispError

#: torchvision's VGG-16 ``features[:9]`` (conv1_1 … relu2_2): the classic perceptual-loss layers.
VGG_BLOCK = ((3, 64), (64, 64), "pool", (64, 128), (128, 128))
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class FilterBank(torch.nn.Module):
    """The shipped fallback F (no download, no training): a fixed multi-scale filter bank.

    At scales 1, 1/2, 1/4 (2×2 average pooling) of the tone-mapped image x = I / (1 + I) the features are the
    image itself and, per colour channel, the Gaussian-smoothed (σ = 1 px) horizontal and vertical derivatives
    and the Laplacian — the responses of the oriented-edge and blob filters that the first layer of an
    ImageNet network learns.  Deterministic: same image, same features."""

    name = "filterbank"

    def __init__(self):
        super().__init__()
        g = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0  # binomial ≈ Gaussian σ = 1
        d = torch.tensor([-1.0, -2.0, 0.0, 2.0, 1.0]) / 8.0  # its derivative
        lap = torch.tensor([[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]])
        lap = torch.nn.functional.pad(lap, (1, 1, 1, 1))
        kernels = torch.stack([torch.outer(g, d), torch.outer(d, g), lap])  # (3, 5, 5)
        self.register_buffer("kernels", kernels[:, None].repeat(3, 1, 1, 1))  # (9, 1, 5, 5), grouped per channel

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = (images / (1 + images)).permute(0, 3, 1, 2)  # (B, 3, H, W)
        feats = []
        for level in range(3):
            if level:
                x = torch.nn.functional.avg_pool2d(x, 2)
            # groups=3: output channels 3c … 3c+2 are channel c's three filters
            feats += [x.flatten(1), torch.nn.functional.conv2d(x, self.kernels.to(x.dtype), padding=2, groups=3).flatten(1)]
        return torch.cat(feats, 1)


class VGGBlock(torch.nn.Module):
    """VGG-16's first two blocks with weights from a local torchvision ``vgg16`` state dict file."""

    name = "vgg16-relu2_2"

    def __init__(self, weights: str):
        super().__init__()
        layers: list[torch.nn.Module] = []
        with torch.random.fork_rng(devices=[]):  # default init, overwritten below: leave the global stream alone
            for spec in VGG_BLOCK:
                layers += ([torch.nn.MaxPool2d(2)] if spec == "pool"
                           else [torch.nn.Conv2d(*spec, 3, padding=1), torch.nn.ReLU()])
        self.features = torch.nn.Sequential(*layers)
        if not os.path.isfile(weights):
            raise RispError(f"{weights}: perceptual weights file not found")
        try:
            state = torch.load(weights, map_location="cpu", weights_only=True)
            state = {k[len("features."):]: v for k, v in state.items() if k.startswith("features.")}
            self.features.load_state_dict({k: v for k, v in state.items() if int(k.split(".")[0]) < len(layers)})
        except Exception as e:  # noqa: BLE001 - unpickler, key and shape errors alike
            raise RispError(f"{weights}: not a torchvision vgg16 state dict ({type(e).__name__})") from None
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = display_gamma(images).permute(0, 3, 1, 2)  # linear → display-like, as ImageNet saw
        return self.features((x - self.mean.to(x.dtype)) / self.std.to(x.dtype)).flatten(1)


#: Below this linear value the display curve x^(1/2.2) continues as the straight line to 0: the power's
#: derivative is infinite at 0, and one exactly black pixel made the perceptual loss's gradient NaN.
GAMMA_TOE = 1e-4


def display_gamma(x: torch.Tensor) -> torch.Tensor:
    """x^(1/2.2) for x ≥ GAMMA_TOE, the straight line from 0 to that point below it (continuous, finite slope);
    negative values count as 0."""
    x = x.clamp(min=0)
    p = 1 / 2.2
    return torch.where(x >= GAMMA_TOE, x.clamp(min=GAMMA_TOE) ** p, x * GAMMA_TOE ** (p - 1))


def feature_extractor(weights: str | None) -> torch.nn.Module:
    """F of the perceptual loss: :class:`VGGBlock` from ``weights`` when given, else :class:`FilterBank`.
    Frozen (no gradients w.r.t. its own parameters); differentiable w.r.t. the images."""
    net = VGGBlock(weights) if weights else FilterBank()
    net.eval()
    for p in net.parameters():
        p.requires_grad_(False)
    return net
