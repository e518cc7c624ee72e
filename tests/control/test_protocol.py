"""The shared observation check of every controller's predict (control.protocol.check_observation)."""
import numpy as np
import pytest

from control.protocol import N_BASE_OBSERVATION, check_observation

OBS = np.array([500.0, 550.0, 6.0, 30.0, 0.1], dtype=np.float32)


def test_valid_observations_convert_exactly():
    batch, single = check_observation(OBS)
    assert single and batch.shape == (1, 5) and batch.dtype == np.float64
    assert np.array_equal(batch[0], OBS.astype(np.float64))
    batch, single = check_observation(np.stack([OBS, OBS]), max_batch=None)
    assert not single and batch.shape == (2, 5)
    batch, single = check_observation(OBS[None])
    assert not single and batch.shape == (1, 5)
    assert check_observation(list(OBS) + [3.0], 6)[0].shape == (1, 6)


def test_non_numeric_observation_is_a_type_error_naming_it():
    for bad in (None, "abc", {"a": 1}):
        with pytest.raises(TypeError, match="observation"):
            check_observation(bad)


@pytest.mark.parametrize("bad, match", [
    (OBS[:3], f"observation must have at least {N_BASE_OBSERVATION} entries"),
    (np.zeros((2, 2, 5)), r"observation must have shape \(n,\) or \(B, n\)"),
    (np.float64(3.0), r"observation must have shape \(n,\) or \(B, n\)"),
    (np.zeros((0, 5)), "empty batch"),
    (np.stack([OBS, OBS]), "single plant"),
    (np.r_[OBS[:4], np.nan], r"observation contains NaN or inf at entries \[4\]"),
    (np.r_[np.inf, OBS[1:]], r"observation contains NaN or inf at entries \[0\]"),
])
def test_bad_observations_are_value_errors_naming_it(bad, match):
    with pytest.raises(ValueError, match=match):
        check_observation(bad, owner="Ctl")


def test_exact_size_when_known_and_names_in_the_message():
    with pytest.raises(ValueError, match=r"observation must have 6 entries \(the environment's observation size\)"):
        check_observation(OBS, 6)
    with pytest.raises(ValueError, match=r"must have 5 entries \(\[a, b, c, d, e\]\)"):
        check_observation(np.zeros(6), 5, names=("a", "b", "c", "d", "e"))
    bad = np.stack([OBS, OBS])
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"\(row, entry\) \[\(1, 2\)\]"):
        check_observation(bad, max_batch=None)


def test_the_input_is_not_modified():
    obs = np.r_[OBS[:4], np.nan]
    before = obs.copy()
    with pytest.raises(ValueError):
        check_observation(obs)
    assert np.array_equal(obs, before, equal_nan=True)
