"""risp-train: the RISP state predictor, its rendering-gradient regularizers, training and evaluation.

    >>> import risp_train
    >>> predictor = risp_train.load("runs/cube/model.pt")   # frozen module: raw images → states

Imports are lazy: importing the package does no work and does not import torch.
"""

from __future__ import annotations


def load(path: str):
    """Load a trained predictor (see :func:`risp_train.predictor.load`)."""
    from .predictor import load as _load

    return _load(path)


__all__ = ["load"]
