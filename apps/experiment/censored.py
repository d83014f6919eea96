"""Rollout counts cut off by the budget: statistics that say when they count sessions never hit.

A session that never hits within a budget of B rollouts is counted as B + 1 rollouts to hit: all
that is known is that it needs more than B. A median or quartile that falls on such a session is
therefore only "> B", and a mean over sessions that include one is only a lower bound ("≥").
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["count_stats", "format_count", "format_counts", "format_mean"]


def count_stats(values: np.ndarray, budget: int) -> dict[str, Any]:
    """Median, mean and quartiles of rollout counts, with what the budget cut off.

    Args:
        values: (sessions,) rollouts to hit per session; budget + 1 for a session that never hit.
        budget: the rollout budget B.

    Returns:
        median, mean, q1, q3 (rollouts; a session that never hit counts as B + 1);
        median_censored, q1_censored, q3_censored: that statistic is a session that never hit,
        so the true value is only known to be > B; mean_censored: the mean counts at least one
        such session, so it is a lower bound; censored_sessions: how many never hit;
        censored_at: B + 1, the count given to them.
    """
    values = np.asarray(values, dtype=float)
    q1, median, q3 = np.percentile(values, [25, 50, 75])
    censored = int(np.sum(values > budget))
    return {
        "median": float(median),
        "mean": float(values.mean()),
        "q1": float(q1),
        "q3": float(q3),
        "median_censored": bool(median > budget),
        "q1_censored": bool(q1 > budget),
        "q3_censored": bool(q3 > budget),
        "mean_censored": censored > 0,
        "censored_sessions": censored,
        "censored_at": budget + 1,
    }


def format_count(stats: Mapping[str, Any], key: str) -> str:
    """`stats[key]` (median, q1 or q3) as text: "> B" when it is a session that never hit."""
    if stats.get(f"{key}_censored"):
        return f"> {int(stats['censored_at']) - 1}"
    return f"{stats[key]:g}"


def format_counts(stats: Mapping[str, Any]) -> str:
    """ "median [q1, q3]", each censored value written "> B"."""
    q1, median, q3 = (format_count(stats, k) for k in ("q1", "median", "q3"))
    return f"{median} [{q1}, {q3}]"


def format_mean(stats: Mapping[str, Any]) -> str:
    """The mean with one decimal, "≥ " before it when it counts a session that never hit."""
    return ("≥ " if stats.get("mean_censored") else "") + f"{stats['mean']:.1f}"
