"""The trained state predictor as a frozen module: raw images in, states (and targets) out.

    >>> import risp_train
    >>> predictor = risp_train.load("runs/cube/model.pt")
    >>> states = predictor(images)                    # (B, H, W, 3) raw linear RGB → (B, S) states
    >>> states, targets = predictor.predict(images)   # also the (B, T) raw targets

``forward`` applies the input normalization, the network, un-normalizes the target and maps it to the
state with the environment's ``target_to_state`` (e.g. atan2 of the sin/cos pairs).  The module is in
eval mode with ``requires_grad=False`` parameters; it stays differentiable w.r.t. the images.
"""

from __future__ import annotations

import torch
from torch import nn

from risp_data.errors import RispError

from .checkpoint import read_checkpoint
from .model import ModelConfig, ResNet18
from .normalization import Normalization


class RispPredictor(nn.Module):
    def __init__(self, net: ResNet18, normalization: Normalization, env_name: str, state_names, target_names,
                 resolution: int, look: str | None = None, spp: int | None = None):
        super().__init__()
        self.net = net
        self.normalization = normalization
        self.env_name = env_name
        self.state_names = tuple(state_names)
        self.target_names = tuple(target_names)
        self.resolution = int(resolution)
        self.look = look  # the training images' look (risp_data.envs.look); None when not recorded
        self.spp = spp  # samples per pixel of the training images; None when not recorded (before 2026-12-01)
        self.sha256: str | None = None  # of the checkpoint file's bytes this predictor was loaded from (load)

    def _check(self, images: torch.Tensor) -> None:
        r = self.resolution
        if images.ndim != 4 or tuple(images.shape[1:]) != (r, r, 3):
            raise RispError(f"images must have shape (B, {r}, {r}, 3) (raw linear RGB), got {tuple(images.shape)}")
        if not torch.isfinite(images).all():
            raise RispError("images contain NaN or inf")

    def predict(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(states (B, S), targets (B, T)) for raw images (B, H, W, 3)."""
        from risp_data.envs import get_environment

        self._check(images)
        dtype = next(self.net.parameters()).dtype
        x = self.normalization.images(images.to(dtype))
        targets = self.normalization.untargets(self.net(x))
        states = get_environment(self.env_name).target_to_state(targets)
        return states, targets

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.predict(images)[0]


def predictor_from_checkpoint(ckpt: dict, path: str = "<checkpoint>") -> RispPredictor:
    try:
        # the layers' default initialisation draws from torch's global generator and is then overwritten:
        # draw in a fork so that loading a model leaves the caller's random stream as it was
        with torch.random.fork_rng(devices=[]):
            net = ResNet18(ModelConfig.from_dict(ckpt["model_config"]))
        net.load_state_dict(ckpt["model"])
        norm = Normalization.from_dict(ckpt["normalization"])
    except (KeyError, RuntimeError, TypeError, ValueError) as e:
        raise RispError(f"corrupt checkpoint {path}: {type(e).__name__}: {str(e).splitlines()[0]}") from None
    p = RispPredictor(net, norm, ckpt["env"], ckpt["state_names"], ckpt["target_names"], ckpt["resolution"],
                      ckpt.get("look"), ckpt.get("spp"))
    p.eval()
    for q in p.parameters():
        q.requires_grad_(False)
    return p


def load(path: str) -> RispPredictor:
    """A frozen, eval-mode :class:`RispPredictor` from a risp-train checkpoint (``weights_only=True``)."""
    ckpt, sha = read_checkpoint(path)
    p = predictor_from_checkpoint(ckpt, path)
    p.sha256 = sha
    return p
