"""Summaries and paired verdicts of FIT over segments (experiments._stats)."""
from __future__ import annotations

import numpy as np
import pytest

from ident.thesis.stats import ALPHA, paired_verdict, summarise


@pytest.mark.parametrize("diff, word", [(np.arange(1, 11), "holds"), (-np.arange(1, 11), "does not hold"),
                                        ([1, -1, 2, -2, 3], "not significant"), ([0, 0, 0], "does not hold")])
def test_verdict_words(diff, word) -> None:
    v = paired_verdict(diff)
    assert v["verdict"] == word and v["n"] == len(diff)
    assert v["wins"] == int(np.sum(np.asarray(diff) > 0))


def test_verdict_is_not_decided_by_one_outlying_segment() -> None:
    # twelve segments better by 5 points, one 300 points worse: the mean says worse, the paired ranks say better
    v = paired_verdict([5.0] * 12 + [-300.0])
    assert v["mean_diff"] < 0 and v["t"] < 0
    assert v["median_diff"] == 5.0 and v["p_wilcoxon"] < ALPHA and v["verdict"] == "holds"


def test_verdict_and_summary_refuse_bad_samples() -> None:
    with pytest.raises(ValueError, match="diff"):
        paired_verdict([])
    with pytest.raises(ValueError, match="diff"):
        paired_verdict([1.0, np.nan])
    with pytest.raises(ValueError, match="empty"):
        summarise([])


def test_summary_figures() -> None:
    s = summarise([1.0, 2.0, 3.0, 4.0, 100.0])
    assert s["median"] == 3.0 and s["q25"] == 2.0 and s["q75"] == 4.0
    assert s["mean"] == 22.0 and s["min"] == 1.0 and s["max"] == 100.0 and s["n"] == 5
