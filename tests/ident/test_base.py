"""ident.base: the shared validators every estimator uses."""
import numpy as np
import pytest

from ident.base import as_2d, as_vector, check_not_constant, check_positive_int


def test_check_not_constant_refuses_only_a_column_constant_over_all_samples():
    y = np.column_stack([np.arange(5.0), np.zeros(5), np.full(5, 2.0)])
    with pytest.raises(ValueError, match=r"^y is constant in column\(s\) \[1, 2\] \(value 0, 2 at all 5 samples\)"
                                         r".*the ARX model cannot be identified"):
        check_not_constant("y", y, "ARX model")
    # zero most of the time (an NH3 slip) is not constant
    slip = np.zeros((100, 1))
    slip[60] = 0.3
    check_not_constant("y", slip)
    # the signal kind and the argument name are the caller's
    with pytest.raises(ValueError, match="^v is constant.*a constant input carries"):
        check_not_constant("v", np.ones((4, 1)), signal="input")


def test_check_not_constant_refuses_overflowing_variance_and_no_columns():
    with pytest.raises(ValueError, match=r"^y has a non-finite variance in column\(s\) \[0\]"):
        check_not_constant("y", as_2d("y", np.array([1e300, -1e300, 1e300])))
    with pytest.raises(ValueError, match="^y has no columns"):
        check_not_constant("y", np.zeros((5, 0)))


def test_as_vector_and_check_positive_int():
    np.testing.assert_array_equal(as_vector("x0", [[1.0], [2.0]], 2), [1.0, 2.0])
    with pytest.raises(ValueError, match=r"^x0 must have 3 values, got shape \(2,\)"):
        as_vector("x0", [1.0, 2.0], 3)
    with pytest.raises(ValueError, match="^x0 contains NaN"):
        as_vector("x0", [1.0, np.nan], 2)
    assert check_positive_int("n", 3.0) == 3
    for bad in (0, -1, 1.5, "two", None):
        with pytest.raises(ValueError, match="^n must be a positive integer"):
            check_positive_int("n", bad)
    with pytest.raises(ValueError, match="^k must be an integer >= 0"):
        check_positive_int("k", -1, minimum=0)


# ------------------------------------------------------------------------------------------ the estimator base
def test_not_fitted_error_is_a_value_and_attribute_error():
    from ident.base import NotFittedError

    assert issubclass(NotFittedError, ValueError) and issubclass(NotFittedError, AttributeError)


def test_every_model_class_shares_one_base_and_one_save_load():
    from ident.base import BaseEstimator
    from ident.greybox import StorageGreyBox
    from ident.hammerstein_wiener import HammersteinWiener
    from ident.linear import ARX, N4SID, OutputError, StateSpacePEM
    from ident.multiple_model import MultipleModel
    from ident.rpem import RecursivePEM
    from ident.stack import OutputStack

    for cls in (RecursivePEM, HammersteinWiener, ARX, OutputError, N4SID, StateSpacePEM, MultipleModel,
                StorageGreyBox, OutputStack):
        assert issubclass(cls, BaseEstimator), cls
        for name in ("get_params", "set_params", "clone", "__repr__", "save"):
            assert getattr(cls, name) is getattr(BaseEstimator, name), (cls, name)
        assert cls.load.__func__ is BaseEstimator.load.__func__, cls


def test_params_clone_and_repr_come_from_the_signature():
    from ident.hammerstein_wiener import HammersteinWiener, Saturation
    from ident.rpem import RecursivePEM

    est = RecursivePEM(n_states=3, alpha=2.0, theta0=[1.0, 2.0])
    params = est.get_params()
    assert params["n_states"] == 3 and params["alpha"] == 2.0 and "R0" in params
    assert repr(est) == "RecursivePEM(n_states=3, alpha=2.0, theta0=[1.0, 2.0])"
    twin = est.clone(alpha=3.0)
    assert type(twin) is RecursivePEM and twin.alpha == 3.0 and twin.n_states == 3
    assert twin.theta0 == est.theta0 and twin.theta0 is not est.theta0  # deep copy, nothing shared
    assert est.set_params(R0=10.0) is est and est.R0 == 10.0
    with pytest.raises(ValueError, match="invalid parameter 'r0' for RecursivePEM; valid parameters: "):
        est.set_params(r0=1.0)
    with pytest.raises(ValueError, match="invalid parameter"):
        est.clone(bogus=1)
    hw = HammersteinWiener(output_block=Saturation(lower=0.0), nb=3)
    again = type(hw)(**hw.get_params())
    assert again.nb == 3 and isinstance(again.output_block, Saturation)
    assert hw.clone().output_block is not hw.output_block
    assert "nb=3" in repr(hw) and "nf=" not in repr(hw)
