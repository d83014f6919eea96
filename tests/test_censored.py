"""Statistics of rollouts-to-hit that say when they count sessions that never hit."""

from __future__ import annotations

import numpy as np

from archery.apps.experiment.censored import count_stats, format_count, format_counts, format_mean


def test_every_session_hit_nothing_is_censored() -> None:
    stats = count_stats(np.array([3, 4, 5, 6]), budget=60)
    assert (stats["median"], stats["q1"], stats["q3"], stats["mean"]) == (4.5, 3.75, 5.25, 4.5)
    assert not any(stats[f"{k}_censored"] for k in ("median", "q1", "q3", "mean"))
    assert format_counts(stats) == "4.5 [3.75, 5.25]" and format_mean(stats) == "4.5"


def test_a_median_on_a_non_hit_is_only_above_the_budget() -> None:
    stats = count_stats(np.array([10, 61, 61, 61, 20]), budget=60)
    assert stats["median"] == 61.0 and stats["median_censored"]
    assert stats["q1"] == 20.0 and not stats["q1_censored"]
    assert stats["censored_sessions"] == 3 and stats["censored_at"] == 61
    assert format_count(stats, "median") == "> 60"
    assert format_counts(stats) == "> 60 [20, > 60]"
    assert format_mean(stats) == "≥ 42.6"  # (10 + 20 + 3 × 61) / 5, a lower bound


def test_one_non_hit_leaves_the_median_exact_but_makes_the_mean_a_bound() -> None:
    stats = count_stats(np.array([5, 6, 7, 61]), budget=60)
    assert not stats["median_censored"] and stats["q3_censored"] is False
    assert stats["mean_censored"] and format_mean(stats) == "≥ 19.8"
