"""Two one-sided permutation tests (TOST) for the pre-registered equivalence studies (issue 76): a known
answer, planted equivalence and planted difference."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.equivalence import equivalence_pvalue


def test_known_answer_two_values_each():
    # b - 10 = [-9, -8]: of the 6 splits of [1, 2, -9, -8] only the observed one reaches a difference of 10
    assert equivalence_pvalue([1.0, 2.0], [1.0, 2.0], 10.0) == pytest.approx((1 / 6, 1 / 6))


def test_planted_equivalence_is_found_with_ten_seeds_each():
    rng = np.random.default_rng(0)
    a, b = 0.058 + 0.004 * rng.standard_normal(10), 0.058 + 0.004 * rng.standard_normal(10)
    p_low, p_high = equivalence_pvalue(a, b, 0.01)
    assert max(p_low, p_high) < 0.05


def test_a_planted_difference_beyond_the_margin_is_not_equivalent():
    rng = np.random.default_rng(1)
    a, b = 0.078 + 0.004 * rng.standard_normal(10), 0.058 + 0.004 * rng.standard_normal(10)
    p_low, p_high = equivalence_pvalue(a, b, 0.01)
    assert p_low < 0.01 and p_high > 0.5  # surely above -margin, not shown below +margin
    assert equivalence_pvalue(b, a, 0.01)[::-1] == pytest.approx((p_low, p_high))  # the mirror image


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="positive margin"):
        equivalence_pvalue([1.0], [1.0], 0.0)
    with pytest.raises(ValueError, match="splits"):
        equivalence_pvalue(np.arange(15.0), np.arange(15.0), 1.0)
