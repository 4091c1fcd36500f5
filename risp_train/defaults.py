"""Defaults that the command line needs before anything heavy is imported (no torch here: ``risp-train --help``
reads them)."""

DEFAULT_REG = "stochastic"  # RISP's regularizer by default (docs/training.md §Calibrated regularizer)

# the names --reg / --preset accept (click lists them in --help); the modules that own them import torch, so they
# are repeated here — tests/test_train_config.py checks that they agree with REGULARIZERS and PRESETS
REG_CHOICES = ("none", "surrogate", "exact", "stochastic")  # risp_train.regularizers.REGULARIZERS
PRESET_CHOICES = ("paper", "cpu")  # risp_train.config.PRESETS
