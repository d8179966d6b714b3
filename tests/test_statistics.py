"""Each statistic against published reference values."""

import math

import numpy as np
import pytest
from scipy import stats
from statsmodels.stats.multitest import multipletests

from server.analysis.statistics import (
    holm,
    krippendorff_alpha_ordinal,
    participants_needed,
    rank_biserial,
    sign_test_p,
    t_interval,
    weighted_kappa,
    wilcoxon_p,
)

# scipy.stats.wilcoxon documentation: Darwin's corn data (via Fisher).
CORN = [6, 8, 14, 16, 23, 24, 28, 29, 41, -48, 49, 56, 60, -67, 75]


def test_wilcoxon_against_scipy_documentation():
    assert stats.wilcoxon(CORN).statistic == 24  # the documented statistic, same call as below
    assert wilcoxon_p(CORN) == pytest.approx(0.041259765625, rel=1e-12)  # exact (no zeros, no ties)
    assert wilcoxon_p([0, 0, 0]) is None and wilcoxon_p([]) is None


def test_wilcoxon_with_ties_and_zeros_is_scipys_exact_permutation_p():
    # Likert means (halves, ties, zeros): scipy's default p is an exhaustive permutation test up to n = 13.
    rng = np.random.default_rng(7)
    for n in range(1, 10):
        for _ in range(6):
            x = rng.integers(-4, 5, n) / 2
            if np.any(x != 0):
                assert wilcoxon_p(x) == pytest.approx(stats.wilcoxon(x, zero_method="pratt").pvalue, rel=1e-12)
    # At n = 13 (scipy takes seconds) by hand: only the flip that keeps every sign reaches the observed sum.
    assert wilcoxon_p([0.5] * 13) == pytest.approx(2 / 2**13, rel=1e-12)
    assert wilcoxon_p([1.0] * 12 + [0.0]) == pytest.approx(2 / 2**12, rel=1e-12)  # the zero is never signed
    assert wilcoxon_p([1.0, -1.0] * 6 + [0.0]) == pytest.approx(1.0)


def test_rank_biserial_of_the_corn_data():
    # (T+ - T-) / (T+ + T-) = (96 - 24) / 120, the value pingouin and R's effectsize report.
    assert rank_biserial(CORN) == pytest.approx(0.6, abs=1e-12)
    assert rank_biserial([0.5, 0, -1.0, 0]) == pytest.approx((1 - 2) / 3)  # zeros dropped before ranking
    assert rank_biserial([0, 0]) is None


def test_sign_test():
    # The binomial test itself against scipy's documentation example ...
    assert stats.binomtest(3, 15, 0.1, alternative="greater").pvalue == pytest.approx(0.184061, abs=1e-6)
    # ... and the sign test by hand: 12 of 15 non-zero signs positive, two-sided exact.
    x = [1] * 12 + [-0.5] * 3 + [0] * 4
    expected = 2 * sum(math.comb(15, k) for k in range(12, 16)) / 2**15
    assert sign_test_p(x) == pytest.approx(expected, rel=1e-12)
    assert sign_test_p([0, 0]) is None


def test_t_interval_against_r_sleep_data():
    # R: t.test(extra ~ group, data = sleep, paired = TRUE): 95 % CI -2.4598858 .. -0.7001142.
    g1 = [0.7, -1.6, -0.2, -1.2, -0.1, 3.4, 3.7, 0.8, 0.0, 2.0]
    g2 = [1.9, 0.8, 1.1, 0.1, -0.1, 4.4, 5.5, 1.6, 4.6, 3.4]
    low, high = t_interval(np.subtract(g1, g2))
    assert low == pytest.approx(-2.4598858, abs=1e-7) and high == pytest.approx(-0.7001142, abs=1e-7)
    assert t_interval([1.0]) is None and t_interval([0.5, 0.5]) == [0.5, 0.5]


def test_holm_against_the_benjamini_hochberg_example():
    ps = [0.0001, 0.0004, 0.0019, 0.0095, 0.0201, 0.0278, 0.0298, 0.0344, 0.0459, 0.3240, 0.4262, 0.5719,
          0.6528, 0.7590, 1.000]
    adjusted = holm(ps)
    assert adjusted[:5] == pytest.approx([0.0015, 0.0056, 0.0247, 0.114, 0.2211], abs=1e-12)
    assert sum(p < 0.05 for p in adjusted) == 3  # Holm rejects 3 at 0.05 (BH would reject 4)
    assert holm([None, 0.01, None, 0.04]) == [None, pytest.approx(0.02), None, pytest.approx(0.04)]


def test_holm_equals_statsmodels_on_unsorted_and_tied_p_values():
    rng = np.random.default_rng(3)
    for size in (1, 2, 7, 30):
        ps = np.round(rng.uniform(0, 0.3, size) ** 2, 3)  # rounded: ties and zeros among them
        assert holm(list(ps)) == pytest.approx(multipletests(ps, method="holm")[1].tolist(), abs=1e-15)


# R irr package, data(anxiety): three raters of 20 subjects (column-major).
ANXIETY = np.array([3, 3, 3, 4, 5, 5, 2, 3, 5, 2, 2, 6, 1, 5, 2, 2, 1, 2, 4, 3,
                    3, 6, 4, 6, 2, 4, 2, 4, 3, 3, 2, 3, 3, 3, 2, 2, 1, 3, 3, 4,
                    2, 1, 4, 4, 3, 2, 1, 6, 1, 1, 1, 2, 3, 3, 1, 1, 3, 3, 2, 2]).reshape(3, 20)


def test_weighted_kappa_against_r_irr_and_sas():
    rater2, rater3 = ANXIETY[1], ANXIETY[2]
    used = sorted(set(rater2) | set(rater3))  # irr's kappa2 tabulates the categories that occur
    # irr::kappa2(anxiety[, 2:3], "squared") = 0.2520325; "equal" (linear) = 0.1459075.
    assert weighted_kappa(rater2, rater3, used, "quadratic") == pytest.approx(0.2520325, abs=1e-7)
    assert weighted_kappa(rater2, rater3, used, "linear") == pytest.approx(0.1459075, abs=1e-7)
    # The full 1..6 scale changes the answer (why the study always passes all five scores).
    assert weighted_kappa(rater2, rater3, range(1, 7), "quadratic") == pytest.approx(0.2298, abs=1e-4)
    # SAS example table [[0, 4, 1], [0, 8, 0], [0, 1, 5]]: linear-weighted kappa 0.4701.
    table = [[0, 4, 1], [0, 8, 0], [0, 1, 5]]
    a = [i for i, row in enumerate(table) for j, n in enumerate(row) for _ in range(n)]
    b = [j for i, row in enumerate(table) for j, n in enumerate(row) for _ in range(n)]
    assert weighted_kappa(a, b, [0, 1, 2], "linear") == pytest.approx(0.4701, abs=1e-4)
    assert weighted_kappa([2, -2], [2, -2]) == pytest.approx(1.0)


def test_krippendorff_alpha_against_krippendorffs_worked_example():
    # Krippendorff (2011), "Computing Krippendorff's alpha-reliability": 4 observers x 12 units.
    nan = None
    data = [[1, 2, 3, 3, 2, 1, 4, 1, 2, nan, nan, nan],
            [1, 2, 3, 3, 2, 2, 4, 1, 2, 5, nan, 3],
            [nan, 3, 3, 3, 2, 3, 4, 2, 2, 5, 1, nan],
            [1, 2, 3, 3, 2, 4, 4, 1, 2, 5, 1, nan]]
    units = [[row[u] for row in data if row[u] is not None] for u in range(12)]
    assert krippendorff_alpha_ordinal(units, values=[1, 2, 3, 4, 5]) == pytest.approx(0.815, abs=5e-4)
    assert krippendorff_alpha_ordinal([[2, 2], [-1, -1], [0, 0]]) == pytest.approx(1.0)
    assert krippendorff_alpha_ordinal([[1]]) is None


def test_participants_needed_for_80_percent_power():
    # d_z = 0.5: the t-test needs 33.4 participants (statsmodels), Wilcoxon 33.4 / (3/pi) -> 35 (G*Power's ARE rule).
    z = np.array([-1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5])
    x = 0.5 + z / z.std(ddof=1)
    assert participants_needed(x) == 35
    assert participants_needed([0.0, 0.0]) is None
