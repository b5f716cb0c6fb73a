"""``geopose bench``: the method's operating points on held-out cases with known
poses, reported in the paper's table shape (``cases`` builds them, ``run``
evaluates one, ``report`` aggregates and draws)."""

from .cases import BenchCase, headsq_case, phantom_case, seed_range, training_seeds
from .report import convergence_figure, markdown, summarise
from .run import BenchSettings, evaluate_case, row_names

__all__ = [
    "BenchCase", "BenchSettings", "convergence_figure", "evaluate_case", "headsq_case", "markdown", "phantom_case",
    "row_names", "seed_range", "summarise", "training_seeds",
]
