"""The parameter count every method family, the trainers, the evaluation and the benchmarks report (one
home, so that a shared module is counted once everywhere)."""

from torch import nn


def count_parameters(model: nn.Module) -> int:
    """Number of parameter scalars; a module shared by two branches is counted once."""
    return sum(p.numel() for p in model.parameters())  # parameters() already removes duplicates
