import numpy as np
import pytest

from ident.excitation import GBN, PRBS, Multisine, RandomSteps, crest_factor, generate_multichannel

GENERATORS = [PRBS(-2, 3, clock_period_s=1.0, order=7), GBN(0, 1, mean_hold_s=5.0), RandomSteps(-1, 1, 1, 5),
              Multisine(rms=0.5, f_min_hz=0.01, f_max_hz=0.2, phases="random")]


@pytest.mark.parametrize("gen", GENERATORS, ids=lambda g: type(g).__name__)
def test_seeded_and_shaped(gen):
    a = gen.generate(500, 0.5, seed=1)
    b = gen.generate(500, 0.5, seed=1)
    c = gen.generate(500, 0.5, seed=2)
    assert a.shape == (500,) and np.all(np.isfinite(a))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_prbs_levels_period_and_hold():
    x = PRBS(-2, 3, clock_period_s=1.0, order=5).generate(2 * 31 * 2, 0.5, seed=0)
    assert set(np.unique(x)) == {-2.0, 3.0}
    bits = x[::2]  # two samples per clock period
    np.testing.assert_array_equal(bits[:31], bits[31:62])  # maximum-length period 2^5 - 1
    assert np.all(x[0::2] == x[1::2])
    # a maximum-length sequence has 16 ones and 15 zeros per period
    assert np.sum(bits[:31] == 3.0) == 16


def test_gbn_mean_hold():
    x = GBN(-1, 1, mean_hold_s=5.0).generate(20000, 0.5, seed=0)
    n_switch = np.count_nonzero(np.diff(x))
    assert 20000 * 0.5 / n_switch == pytest.approx(5.0, rel=0.1)


def test_random_steps_range_and_holds():
    x = RandomSteps(2.0, 4.0, 1.0, 3.0).generate(3000, 0.5, seed=0)
    assert x.min() >= 2.0 and x.max() <= 4.0
    edges = np.flatnonzero(np.diff(x)) + 1
    holds = np.diff(edges)
    assert holds.min() >= 2 and holds.max() <= 6
    lv = RandomSteps(0, 1, 1, 2, n_levels=3).generate(200, 1.0, seed=0)
    assert set(np.unique(lv)) <= {0.0, 0.5, 1.0}


def test_multisine_rms_and_band():
    dt, n = 0.5, 1000
    ms = Multisine(rms=2.0, f_min_hz=0.05, f_max_hz=0.3, offset=1.0)
    x = ms.generate(n, dt)
    assert np.mean(x) == pytest.approx(1.0, abs=1e-9)
    assert np.std(x) == pytest.approx(2.0, rel=1e-9)
    spec = np.abs(np.fft.rfft(x - 1.0)) ** 2
    f = np.fft.rfftfreq(n, dt)
    inband = (f >= 0.05 - 1e-9) & (f <= 0.3 + 1e-9)
    assert spec[~inband].sum() < 1e-12 * spec.sum()
    assert crest_factor(x) < 2.5  # Schroeder phases keep the crest factor low


def test_multichannel_independent_and_reproducible():
    sigs = [GBN(mean_hold_s=2.0), GBN(mean_hold_s=2.0)]
    a = generate_multichannel(sigs, 300, 0.5, seed=4)
    assert a.shape == (300, 2)
    assert not np.array_equal(a[:, 0], a[:, 1])
    np.testing.assert_array_equal(a, generate_multichannel(sigs, 300, 0.5, seed=4))


def test_bad_arguments():
    with pytest.raises(ValueError, match="shorter than the sample time"):
        PRBS(clock_period_s=0.1).generate(10, 0.5)
    with pytest.raises(ValueError, match="order"):
        PRBS(order=40).generate(10, 0.5)
    with pytest.raises(ValueError, match="n_samples"):
        GBN().generate(0, 0.5)
    with pytest.raises(ValueError, match="no frequency"):
        Multisine(f_min_hz=10.0, f_max_hz=11.0).generate(100, 0.5)
