"""Eq. 16-19 on hand-made maps."""

import numpy as np
import pytest

from uavsearch.errors import UavsearchError
from uavsearch.search.metrics import average_metrics, cell_correct, confusion_counts, map_accuracy, map_f1


def test_counts_accuracy_and_f1_by_hand():
    # 10 cells, 3 occupied (0, 1, 2). Predictions: TP on 0, FN on 1 and 2, FP on 3, the rest TN.
    y = np.zeros(10, int)
    y[:3] = 1
    p = np.full(10, 0.1)
    p[0] = 0.9
    p[3] = 0.7
    c = confusion_counts(p, y)
    assert (c.tp, c.tn, c.fp, c.fn) == (1, 6, 1, 2)
    assert map_accuracy(p, y) == pytest.approx(0.7)
    assert map_f1(p, y) == pytest.approx(2 / (2 + 1 + 2))


def test_exactly_half_is_wrong_for_either_label():
    y = np.array([0, 1])
    p = np.array([0.5, 0.5])
    assert not cell_correct(p, y).any()
    c = confusion_counts(p, y)
    assert (c.tp, c.tn, c.fp, c.fn) == (0, 0, 1, 1)
    assert map_accuracy(p, y) == 0.0


def test_f1_defined_as_one_for_empty_map_with_no_predictions():
    assert map_f1(np.full(100, 0.2), np.zeros(100)) == 1.0
    assert map_f1(np.r_[0.8, np.full(99, 0.2)], np.zeros(100)) == 0.0  # a false alarm on an empty map


def test_average_over_maps():
    y = np.array([[1, 0, 0, 0], [1, 1, 0, 0]])
    p = np.array([[0.9, 0.1, 0.1, 0.1], [0.9, 0.1, 0.1, 0.1]])
    aacc, af1 = average_metrics(p, y)
    assert aacc == pytest.approx((1.0 + 0.75) / 2)
    assert af1 == pytest.approx((1.0 + 2 / 3) / 2)


def test_bad_input():
    with pytest.raises(UavsearchError):
        map_accuracy(np.zeros(3), np.zeros(4))
    with pytest.raises(UavsearchError, match="NaN"):
        map_f1(np.array([np.nan]), np.array([1]))
