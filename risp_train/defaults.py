"""Defaults that the command line needs before anything heavy is imported (no torch here: ``risp-train --help``
reads them)."""

DEFAULT_REG = "stochastic"  # RISP's regularizer by default (docs/training.md §Calibrated regularizer)
