"""Confidence intervals and paired tests of success proportions (what the reports quote)."""

from __future__ import annotations

import math


def mcnemar_exact_p(only_a: int, only_b: int) -> float:
    """Two-sided exact McNemar p-value of paired outcomes: the binomial test at 1/2 of the
    discordant pairs (`only_a` succeeded only under A, `only_b` only under B)."""
    if only_a < 0 or only_b < 0:
        raise ValueError(f"mcnemar_exact_p: need counts >= 0, got {only_a}, {only_b}")
    n = only_a + only_b
    if n == 0:
        return 1.0
    k = min(only_a, only_b)
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n
    return min(1.0, 2 * tail)


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95% for the default z).

    Chosen over the normal approximation because it stays inside [0, 1] and is sensible
    at 0/n and n/n, which are common here (e.g. 40 isolation trials, all successful).

    Args:
        successes: Number of successes, 0 <= successes <= n.
        n: Number of trials; 0 gives the uninformative (0.0, 1.0).
        z: Standard-normal quantile.

    Returns:
        (lower, upper).
    """
    if n < 0 or successes < 0 or successes > n:
        raise ValueError(f"wilson_interval: need 0 <= successes <= n, got successes={successes}, n={n}")
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    z2 = z * z
    denom = 1.0 + z2 / n
    center = (p + z2 / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / denom
    # Exact bounds at the ends (the formula gives them up to rounding).
    lo = 0.0 if successes == 0 else max(0.0, center - half)
    hi = 1.0 if successes == n else min(1.0, center + half)
    return (lo, hi)
