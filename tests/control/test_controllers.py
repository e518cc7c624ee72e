"""Every controller satisfies the policy protocol; a failing MPC solve returns the fallback dose and is counted;
the oracle's collocation equations are the plant's step (scr_env.casadi_model)."""
import numpy as np
import pytest

from control.baselines import FeedforwardPI, LookupTableDosing
from control.evaluation import evaluate
from control.models import FirstPrinciplesModel, IdentifiedModelAdapter
from control.mpc import NonlinearMPC
from control.protocol import PolicyPredictor, action_to_rate
from ident.greybox import StorageGreyBox


def _identified_mpc(**kw):
    m = StorageGreyBox.from_params(np.zeros(11), np.array([0.95, 1.0]), n_cells=2)
    adapter = IdentifiedModelAdapter(m, np.zeros(4), np.ones(4), np.zeros(3), np.ones(3), measurement_noise=100.0,
                                     process_noise=np.array([1e-6, 1e-6, 0.5]),
                                     state_bounds=(np.array([0, 0, 250.0]), np.array([1, 1, 900.0])),
                                     initial_state=lambda obs: np.array([0.0, 0.0, obs[1]]))
    return NonlinearMPC(adapter, horizon=4, stage_steps=2, **kw)


CONTROLLERS = {
    "lookup_table": LookupTableDosing,
    "pi": FeedforwardPI,
    "mpc_oracle": lambda: NonlinearMPC(FirstPrinciplesModel(), horizon=3, stage_steps=2, preview=True),
    "mpc_identified": _identified_mpc,
}


@pytest.mark.parametrize("name", list(CONTROLLERS))
def test_controller_satisfies_protocol(name):
    policy = CONTROLLERS[name]()
    assert isinstance(policy, PolicyPredictor)
    res = evaluate(policy, cycles=("whsc",), max_steps=10, name=name)[0]
    assert res.timing["policy_time_ms_median"] > 0
    if name.startswith("mpc"):
        assert res.stats["solves"] == 10 and res.stats["solver_failures"] == 0
    a, state = policy.predict(np.array([500.0, 550.0, 6.0, 30.0, 0.0], dtype=np.float32))
    assert a.shape == (1,) and -1.0 <= float(a[0]) <= 1.0 and state is None


def test_failing_solve_returns_fallback_and_is_counted():
    lut = LookupTableDosing()
    mpc = _identified_mpc(fallback=lut, max_rate_change_g_s2=100.0, solver_options={"ipopt.max_iter": 1})
    res = evaluate(mpc, cycles=("whsc",), max_steps=10, record_trajectory=True)[0]
    assert res.stats["solver_failures"] == 10
    # every dose was the look-up table's (the rate limit is wide open here)
    from scr_env.envs.urea_scr import UreaSCREnv

    env = UreaSCREnv(cycle="whsc")
    obs, _ = env.reset(seed=0)
    expected = action_to_rate(lut.predict(obs)[0])
    assert abs(res.trajectory["adblue_g_s"][0] - expected) < 1e-5


def test_model_error_falls_back_not_raises():
    mpc = _identified_mpc()
    mpc.estimator.make_step = lambda *a, **k: (_ for _ in ()).throw(RuntimeError("broken model"))
    res = evaluate(mpc, cycles=("whsc",), max_steps=5)[0]
    assert res.stats["solver_failures"] == 5


def test_slip_guard_doses_nothing_on_failed_solves_while_the_nh3_sensor_reads_slip():
    from scr_env.envs.urea_scr import UreaSCREnv

    lut = LookupTableDosing()
    mpc = _identified_mpc(fallback=lut, max_rate_change_g_s2=100.0, slip_guard=(5, 10.0))
    env = UreaSCREnv(cycle="whsc", nh3_sensor=True)
    env.reset(seed=0)
    mpc.attach(env)
    mpc.estimator.make_step = lambda *a, **k: (_ for _ in ()).throw(RuntimeError("broken model"))  # every solve fails
    slipping = np.array([500.0, 550.0, 6.0, 30.0, 0.0, 25.0])
    clean = slipping.copy()
    clean[5] = 2.0
    a, _ = mpc.predict(slipping, episode_start=True)
    assert action_to_rate(a[0]) == 0.0                      # the fallback would dose; the guard stops it
    a, _ = mpc.predict(clean)
    assert action_to_rate(a[0]) == pytest.approx(lut.dose_g_s(clean), rel=1e-6) and lut.dose_g_s(clean) > 0
    assert mpc.stats()["slip_guarded_steps"] == 1 and mpc.stats()["solver_failures"] == 2
    # an environment without the NH3 sensor is refused, and so are malformed guards
    with pytest.raises(ValueError, match="slip_guard"):
        mpc.attach(UreaSCREnv(cycle="whsc"))
    for bad in ((-1, 10.0), (5, float("nan")), (5, -1.0), (2.5, 10.0)):
        with pytest.raises(ValueError, match="slip_guard"):
            _identified_mpc(slip_guard=bad)


def test_oracle_collocation_equals_plant_step():
    """At the plant's next state (casadi_model.catalyst_step, implicit Euler) the oracle's residual vanishes."""
    import casadi as ca

    from scr_env.casadi_model import catalyst_step
    from scr_env.envs.urea_scr import UreaSCREnv
    from scr_env.params import CatalystParams

    env = UreaSCREnv(cycle="whsc")
    env.reset(seed=0)
    model = FirstPrinciplesModel()
    model.attach(env)
    n, h = model.n_cells, 2.0
    theta = np.linspace(0.1, 0.5, n)
    temps = np.full(n, 560.0)
    d = np.array([8.0, 560.0, 800.0, 0.4])
    dose = 0.6
    x_next, y = catalyst_step(CatalystParams(), dt=h)(np.r_[theta, temps], [*d, dose, 0.10])
    x_next = np.asarray(x_next).ravel()
    # the oracle's stage parameters at those end-of-step temperatures
    model._env = type("E", (), {"state": {"nh3_coverage": theta, "temperature_k": temps}})()
    model.use_preview = False
    pst, _ = model.stage_parameters(None, d[None, :], h, h)
    xs, us = ca.SX.sym("x", n), ca.SX.sym("u")
    r = ca.Function("r", [xs, us], [model.residual(xs, ca.DM(theta), us, d, ca.DM(pst[0]), h),
                                    model.outputs(xs, None, us, d, ca.DM(pst[0]))])
    res, out = r(x_next[:n], dose)
    assert np.max(np.abs(np.asarray(res))) < 1e-6
    y = np.asarray(y).ravel()
    assert np.allclose(np.asarray(out).ravel(), [y[0] + y[1], y[2]], rtol=1e-6, atol=1e-6)


# ------------------------------------------------------------------------------------------ observation checks
OBS = np.array([500.0, 550.0, 6.0, 30.0, 0.0], dtype=np.float32)


def _episode(rng_seed=0, n=60):
    """A plausible observation sequence (hot catalyst, varying NOx, flow and sensor)."""
    rng = np.random.default_rng(rng_seed)
    obs = np.tile(OBS.astype(np.float64), (n, 1))
    obs[:, 0] = 400.0 + 300.0 * rng.random(n)
    obs[:, 1] = 540.0 + np.linspace(0.0, 60.0, n)
    obs[:, 2] = 5.0 + 3.0 * rng.random(n)
    obs[:, 3] = 5.0 + 80.0 * rng.random(n)
    return obs.astype(np.float32)


def _bad_observations(n_obs=5):
    nan = np.array(OBS, dtype=np.float64)
    nan[3] = np.nan
    inf = np.array(OBS, dtype=np.float64)
    inf[0] = np.inf
    return [(nan, ValueError, "observation contains NaN"), (inf, ValueError, "observation contains NaN or inf"),
            (OBS[:3], ValueError, "observation must have"), (None, TypeError, "observation")]


def test_lookup_table_takes_batches_and_rejects_bad_observations():
    lut = LookupTableDosing()
    a, _ = lut.predict(OBS)
    assert a.shape == (1,) and a.dtype == np.float32
    obs = _episode(n=4)
    batch, _ = lut.predict(obs)
    assert batch.shape == (4, 1) and batch.dtype == np.float32
    assert np.array_equal(batch[:, 0], [lut.predict(o)[0][0] for o in obs])
    one, _ = lut.predict(OBS[None])
    assert one.shape == (1, 1) and one[0, 0] == a[0]
    for bad, err, match in _bad_observations():
        with pytest.raises(err, match=match):
            lut.predict(bad)
    bad = obs.copy()
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"observation contains NaN or inf at \(row, entry\) \[\(2, 1\)\]"):
        lut.predict(bad)
    # after attach the exact size of the environment's observation is required
    from scr_env.envs.urea_scr import UreaSCREnv

    lut.attach(UreaSCREnv(cycle="whsc", nh3_sensor=True))
    with pytest.raises(ValueError, match="observation must have 6 entries"):
        lut.predict(OBS)
    assert lut.predict(np.r_[OBS, 2.0])[0][0] == a[0]


def test_pi_rejects_bad_observations_and_batches_without_touching_its_state():
    obs = _episode()
    ref = FeedforwardPI()
    expected = [ref.predict(o, episode_start=np.array([k == 0]))[0] for k, o in enumerate(obs)]
    pi = FeedforwardPI()
    got = []
    for k, o in enumerate(obs):
        if k in (5, 30):  # bad calls mid-episode (also flagged as an episode start: must not reset either)
            for bad, err, match in _bad_observations() + [(np.stack([o, o]), ValueError, "single plant")]:
                with pytest.raises(err, match=match):
                    pi.predict(bad, episode_start=np.array([True]))
        got.append(pi.predict(o, episode_start=np.array([k == 0]))[0])
    assert all(np.array_equal(g, e) for g, e in zip(got, expected, strict=True))
    assert pi.stats() == ref.stats()
    # one plant as a (1, n) batch: action (1, 1), the same number
    a, _ = FeedforwardPI().predict(obs[0][None], episode_start=np.array([True]))
    assert a.shape == (1, 1) and a[0, 0] == expected[0][0]


def test_pi_after_attach_wants_the_environment_s_observation_size():
    from scr_env.envs.urea_scr import UreaSCREnv

    pi = FeedforwardPI()
    pi.attach(UreaSCREnv(cycle="whsc"))
    with pytest.raises(ValueError, match="observation must have 5 entries"):
        pi.predict(np.r_[OBS, 1.0])


def _mpc_counters(mpc):
    s = mpc.stats()
    return {k: s[k] for k in ("solver_failures", "solves", "solver_suboptimal", "slip_guarded_steps")}


def test_mpc_rejects_bad_observations_before_solving_or_counting():
    """predict(None), obs[:3], a batch of two, NaN: clear errors, not a 'solver failure' with a plausible dose;
    the estimator, the warm start and the counters are untouched (the next doses equal an undisturbed run's)."""
    obs = _episode(n=8)
    ref = _identified_mpc()
    expected = [ref.predict(o, episode_start=np.array([k == 0]))[0] for k, o in enumerate(obs)]
    mpc = _identified_mpc()
    for k, o in enumerate(obs):
        if k == 3:
            before = (_mpc_counters(mpc), mpc.estimator.ekf_.x_.copy(), mpc.estimator.ekf_.P_.copy(), mpc._u_prev)
            for bad, err, match in _bad_observations() + [(np.stack([o, o]), ValueError, "single plant")]:
                with pytest.raises(err, match=match):
                    mpc.predict(bad)
            after = (_mpc_counters(mpc), mpc.estimator.ekf_.x_, mpc.estimator.ekf_.P_, mpc._u_prev)
            assert before[0] == after[0] and np.array_equal(before[1], after[1])
            assert np.array_equal(before[2], after[2]) and before[3] == after[3]
        a, _ = mpc.predict(o, episode_start=np.array([k == 0]))
        assert np.array_equal(a, expected[k])
    assert _mpc_counters(mpc) == _mpc_counters(ref)


def test_mpc_one_plant_as_a_batch_of_one():
    a, _ = _identified_mpc().predict(OBS[None], episode_start=np.array([True]))
    b, _ = _identified_mpc().predict(OBS, episode_start=np.array([True]))
    assert a.shape == (1, 1) and b.shape == (1,) and a[0, 0] == b[0]


def test_mpc_observation_size_before_and_after_attach():
    from scr_env.envs.urea_scr import UreaSCREnv

    guarded = _identified_mpc(slip_guard=(5, 10.0))  # reads obs[5]: needs the NH3 sensor entry
    with pytest.raises(ValueError, match="observation must have at least 6 entries"):
        guarded.predict(OBS)
    mpc = _identified_mpc()
    mpc.attach(UreaSCREnv(cycle="whsc"))
    with pytest.raises(ValueError, match="observation must have 5 entries"):
        mpc.predict(np.r_[OBS, 1.0])


@pytest.mark.parametrize("error, counted", [
    (RuntimeError("casadi: solver error"), True),
    (np.linalg.LinAlgError("singular innovation covariance"), True),
    (FloatingPointError("overflow"), True),
    (ZeroDivisionError("float division by zero"), True),
    (ValueError("a bug, not a bad solve"), False),
    (TypeError("a bug"), False),
    (IndexError("a bug"), False),
    (KeyError("a bug"), False),
])
def test_mpc_falls_back_on_numerical_failures_only(error, counted):
    lut = LookupTableDosing()
    mpc = _identified_mpc(fallback=lut, max_rate_change_g_s2=100.0)

    def broken(*a, **k):
        raise error

    mpc.estimator.make_step = broken
    if counted:
        a, _ = mpc.predict(OBS, episode_start=np.array([True]))
        assert action_to_rate(a[0]) == pytest.approx(lut.dose_g_s(OBS), rel=1e-6)
        assert mpc.stats()["solver_failures"] == 1
    else:
        with pytest.raises(type(error), match="bug"):
            mpc.predict(OBS, episode_start=np.array([True]))


def test_identified_nmpc_survives_a_nan_reading_on_the_gym_env():
    """The review's reproduction: one NaN tailpipe reading used to make the EKF state NaN, and the NMPC stopped
    dosing for the rest of the episode without counting a failure. Now the reading is refused (ValueError naming
    the observation), and the episode goes on exactly as if it had not been offered."""
    import gymnasium as gym

    import scr_env  # noqa: F401  (registers scr_env/UreaSCR-v0)

    def run(inject):
        env = gym.make("scr_env/UreaSCR-v0", cycle="whsc")
        obs, _ = env.reset(seed=0)
        mpc = _identified_mpc()
        mpc.attach(env.unwrapped)
        actions = []
        for k in range(12):
            if inject and k == 6:
                bad = np.array(obs, dtype=np.float64)
                bad[3] = np.nan
                with pytest.raises(ValueError, match="observation contains NaN"):
                    mpc.predict(bad)
            a, _ = mpc.predict(obs, episode_start=np.array([k == 0]))
            actions.append(a)
            obs, *_ = env.step(a)
        env.close()
        return np.array(actions), mpc.stats()["solver_failures"], mpc.estimator.ekf_.x_

    clean, fail_clean, x_clean = run(False)
    dirty, fail_dirty, x_dirty = run(True)
    assert np.array_equal(clean, dirty) and fail_clean == fail_dirty and np.array_equal(x_clean, x_dirty)
    assert np.all(np.isfinite(x_dirty)) and action_to_rate(dirty[-1][0]) > 0.0


# ------------------------------------------------------------------------------------------------ feedforward
def test_one_feedforward_law_for_every_feedforward():
    """The look-up table, FeedforwardDosing and the identification data's dosing compute their dose with
    feedforward_dose_g_s: the same numbers for the same ANR."""
    from control.baselines import FeedforwardDosing, feedforward_dose_g_s
    from ident.plant_data import feedforward_adblue_g_s
    from scr_env.constants import NH3_MOL_PER_G_ADBLUE

    obs = np.array([800.0, 600.0, 8.0, 30.0, 0.0])
    ref = 0.9 * (800.0 * 1e-6 * 8.0) / NH3_MOL_PER_G_ADBLUE
    assert feedforward_dose_g_s(800.0, 8.0, 0.9) == ref == feedforward_adblue_g_s(800.0, 8.0, 0.9)
    assert FeedforwardDosing(0.9).dose_g_s(obs) == ref
    lut = LookupTableDosing()
    assert lut.dose_g_s(obs) == min(feedforward_dose_g_s(800.0, 8.0, lut.target_anr(600.0, 8.0)), 3.0)
    assert feedforward_dose_g_s(-5.0, 8.0) == 0.0 and feedforward_dose_g_s(500.0, -1.0) == 0.0
    np.testing.assert_array_equal(feedforward_dose_g_s(np.array([800.0, 0.0]), 8.0, 0.9), [ref, 0.0])


def test_feedforward_dosing_ramp_and_checks():
    from control.baselines import FeedforwardDosing

    ramp = FeedforwardDosing(anr=0.9, ramp_start_k=473.15, ramp_width_k=50.0)
    assert ramp.target_anr(450.0) == 0.0 and ramp.target_anr(600.0) == 0.9
    assert ramp.target_anr(498.15) == pytest.approx(0.45)
    a, _ = ramp.predict(np.stack([OBS, OBS]))
    assert a.shape == (2, 1)
    res = evaluate(ramp, cycles=("whsc",), max_steps=20)[0]
    assert res.timing["policy_time_ms_median"] >= 0
    for bad in ({"anr": -0.1}, {"anr": float("nan")}, {"ramp_start_k": 473.0, "ramp_width_k": 0.0},
                {"max_rate_g_s": 0.0}):
        with pytest.raises(ValueError):
            FeedforwardDosing(**bad)
    with pytest.raises(ValueError, match="NaN"):
        ramp.predict(np.array([np.nan, 550.0, 6.0, 30.0, 0.0]))
