"""The NEES consistency test: bounds for correlated frames, checked on filters consistent by construction."""

import numpy as np
import pytest

from tagloc.eval.consistency import calibrate, chi2_mean_bounds, nees_blocks, nees_test, simulate_nees


def test_blocks_sum_frames_nees_and_squares():
    t = np.array([0.0, 1.0, 4.9, 5.0, 12.0])
    b = nees_blocks(t, np.array([1.0, 2.0, 3.0, 4.0, 5.0]), block_s=5.0)
    assert b.tolist() == [[3, 6, 14], [1, 4, 16], [1, 5, 25]]  # the empty 5-10 s block is left out


def test_independent_frames_are_worth_about_their_number():
    rng = np.random.default_rng(3)
    nees = rng.chisquare(2, 6000)
    test = nees_test(nees_blocks(np.arange(6000) / 30.0, nees))
    assert test.effective_samples == pytest.approx(6000, rel=0.35)
    assert test.mean == pytest.approx(nees.mean())
    assert test.bounds_independent == pytest.approx(chi2_mean_bounds(6000))


def test_repeated_frames_count_once():
    rng = np.random.default_rng(4)
    nees = np.repeat(rng.chisquare(2, 400), 30)  # each independent value held for 1 s at 30 fps
    test = nees_test(nees_blocks(np.arange(len(nees)) / 30.0, nees))
    assert test.effective_samples == pytest.approx(400, rel=0.35)
    lo, hi = test.bounds_effective
    assert lo < 1.85 and hi > 2.15  # wider than for 12000 frames ...
    assert test.bounds_independent[1] - test.bounds_independent[0] < 0.15  # ... which would be this tight


def test_verdict_names_the_side():
    def verdict(scale):
        rng = np.random.default_rng(5)
        nees = scale * rng.chisquare(2, 3000)
        return nees_test(nees_blocks(np.arange(3000) / 30.0, nees)).verdict

    assert verdict(1.0) == "consistent"
    assert verdict(0.6) == "conservative"
    assert verdict(1.6) == "overconfident"


def test_calibration_on_filters_consistent_by_construction():
    rates = calibrate(trials=100, seed=0, scales=(1.0, 0.5, 2.0))
    ind, eff = rates[1.0]
    assert ind > 0.5  # the independent-frames bound throws out most honest runs
    assert eff < 0.2  # the effective bound keeps most of them (nominal 5 %: it leans strict)
    assert rates[0.5][1] > 0.9 and rates[2.0][1] > 0.9  # and catches a covariance off by 2


def test_the_calibration_filter_is_consistent_from_its_first_frame():
    """The filter the calibration runs must average NEES 2 in every block, its first included: a truth
    started exactly at the filter's start (not drawn from its stated prior) averaged 1.63 in the
    first 5 s block and 1.91 over the run."""
    runs = np.stack(simulate_nees(np.random.default_rng(7), 2000))  # (runs, 4 blocks, 3)
    per_block = runs[:, :, 1].sum(axis=0) / runs[:, :, 0].sum(axis=0)
    assert per_block == pytest.approx(2.0, abs=0.08)
    assert runs[:, :, 1].sum() / runs[:, :, 0].sum() == pytest.approx(2.0, abs=0.05)


def test_empty_input():
    test = nees_test(np.zeros((0, 3)))
    assert test.frames == 0 and np.isnan(test.mean) and test.verdict == "no data"


def test_a_lone_walks_few_blocks_widen_its_bounds_and_one_block_judges_nothing():
    """Four 5 s blocks estimate the mean's variance loosely: the bounds widen by t(3) / z, so a lone
    20 s run of an honest filter is rejected about as often as nominal (19 % before); one block
    cannot estimate it at all."""
    ind, eff = calibrate(trials=200, sessions=1, seed=0, scales=(1.0,))[1.0]
    assert eff < 0.1
    rng = np.random.default_rng(6)
    nees = rng.chisquare(2, 120)  # 4 s: one block
    test = nees_test(nees_blocks(np.arange(120) / 30.0, nees))
    assert test.verdict == "too short" and np.isfinite(test.bounds_independent).all()
