"""``independent``: no sharing at all; every worker learns alone (the baseline federation must beat)."""

from chief.strategies.base import Strategy, no_gradient

STRATEGY = Strategy(
    name="independent",
    summary="no sharing: each worker learns alone (the baseline)",
    aggregate=no_gradient,
    keep_weight=lambda progress: None,
    tolerates=lambda n: n,
    robustness="nothing is shared, so nothing a worker sends reaches another",
    shares=False,
)
