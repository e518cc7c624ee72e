"""The simulated benchmark systems: seeded, shaped like the public data sets, and showing their nonlinearity."""
import numpy as np
import pytest

from ident.benchmarks import SIMULATED_BENCHMARKS, simulated_benchmark
from ident.benchmarks.simulated import TANKS_PARAMETERS


@pytest.mark.parametrize("name", sorted(SIMULATED_BENCHMARKS))
def test_records_are_seeded_and_shaped(name):
    a = simulated_benchmark(name, seed=3, n_estimation=64, n_validation=32)
    b = simulated_benchmark(name, seed=3, n_estimation=64, n_validation=32)
    c = simulated_benchmark(name, seed=4, n_estimation=64, n_validation=32)
    assert a.estimation.u.shape == (64, 1) and a.validation.y.shape == (32, 1)
    assert a.estimation.dt == a.sampling_period == a.validation.dt
    np.testing.assert_array_equal(a.estimation.y, b.estimation.y)
    np.testing.assert_array_equal(a.validation.u, b.validation.u)
    assert not np.array_equal(a.estimation.u, c.estimation.u)
    assert not np.array_equal(a.estimation.u, a.validation.u)  # independent realisations


def test_unknown_name_and_bad_lengths_are_refused():
    with pytest.raises(ValueError, match="unknown simulated benchmark"):
        simulated_benchmark("silverbox")
    with pytest.raises(ValueError, match="n_estimation"):
        simulated_benchmark("cascaded_tanks", n_estimation=0)


def test_tanks_overflow_and_drive_sensor_ignores_sign():
    tanks = simulated_benchmark("cascaded_tanks")
    assert 0.02 < tanks.estimation.meta["overflow_fraction"] < 0.3  # the hard nonlinearity is exercised
    assert tanks.estimation.y.max() < TANKS_PARAMETERS["level_max_v"] + 0.1
    drive = simulated_benchmark("coupled_drives", n_estimation=500, n_validation=100)
    y = drive.estimation.y[:, 0]
    assert y.min() > -0.1 and np.mean(y < 0.1) > 0.02  # |v| + noise: near zero where the speed changes sign


def test_duffing_is_band_limited_and_periodic():
    d = simulated_benchmark("duffing_oscillator", n_estimation=4096, n_validation=1024)
    spec = np.abs(np.fft.rfft(d.estimation.u[:, 0]))
    f = np.fft.rfftfreq(4096, d.sampling_period)
    assert spec[f > 201.0].max() < 1e-9 * spec.max()
    assert spec[2::2].max() < 1e-9 * spec.max()  # odd multisine: even lines empty
