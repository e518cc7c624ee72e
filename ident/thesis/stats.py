"""Statistics of the multi-segment studies: summaries and paired verdicts of validation FIT over segments.

FIT is bounded above by 100 % but not below (a validation part whose output barely moves gives -200 % for a small
absolute error, a diverging simulation -1e5 %), so a few segments decide a mean and an SD. The summaries lead with
the median and quartiles, and the paired verdicts use the one-sided Wilcoxon signed-rank test, which weighs each
segment by the rank of its difference, not its size.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from scipy import stats

#: One-sided significance level of :func:`paired_verdict`.
ALPHA = 0.05


def summarise(values: Any) -> dict[str, float]:
    """Median, quartiles, mean, SD, min and max of a sample of FIT values."""
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        raise ValueError("cannot summarise an empty sample")
    q25, med, q75 = np.percentile(v, [25, 50, 75])
    return {"n": int(v.size), "median": float(med), "q25": float(q25), "q75": float(q75), "mean": float(v.mean()),
            "sd": float(v.std(ddof=1)) if v.size > 1 else 0.0, "min": float(v.min()), "max": float(v.max())}


def paired_verdict(diff: Any, alpha: float = ALPHA) -> dict[str, Any]:
    """Does A beat B, from the paired differences ``FIT(A) - FIT(B)`` over segments?

    "holds" when the one-sided Wilcoxon signed-rank test gives p < ``alpha``; "not significant" when the median
    difference is positive but p >= ``alpha``; "does not hold" when the median difference is zero or negative.
    The mean difference and its t statistic are reported beside it.
    """
    d = np.asarray(diff, dtype=float)
    if d.size == 0 or not np.all(np.isfinite(d)):
        raise ValueError("diff must be a non-empty array of finite paired differences")
    mean, median = float(d.mean()), float(np.median(d))
    se = float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else float("inf")
    t = mean / se if se > 0 else (float("inf") if mean > 0 else 0.0)
    p = float(stats.wilcoxon(d, alternative="greater").pvalue) if np.any(d != 0) else 1.0
    word = "holds" if median > 0 and p < alpha else ("not significant" if median > 0 else "does not hold")
    return {"median_diff": median, "mean_diff": mean, "se": se, "t": t, "p_wilcoxon": p,
            "wins": int(np.sum(d > 0)), "n": int(d.size), "verdict": word}
