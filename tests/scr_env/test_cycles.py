"""Drive cycles and SCR-inlet traces (scr_env.cycles)."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from scr_env.cycles import (
    ExhaustTrace,
    available_cycles,
    denormalise,
    from_csv,
    load_cycle,
    random_cycle,
)
from scr_env.engine import EngineParams, full_load_torque_nm, motoring_torque_nm

ENGINE = EngineParams()


@pytest.fixture(scope="module")
def whtc() -> ExhaustTrace:
    return load_cycle("whtc", dt=0.5)


@pytest.fixture(scope="module")
def whtc_cold() -> ExhaustTrace:
    return load_cycle("whtc", dt=0.5, cold_start=True)


# ------------------------------------------------------------------------------------------------ shape and grid
def test_available_cycles():
    assert available_cycles() == ("whtc", "whsc", "random", "random_modes")
    assert load_cycle("random_modes", seed=3, duration_s=300.0).name == "random-modes-3"
    with pytest.raises(ValueError, match="seed"):
        load_cycle("random_modes")


def test_whtc_and_whsc_lengths(whtc):
    assert whtc.n_steps == 3600 and whtc.dt == 0.5
    assert whtc.time_s[0] == 0.0 and whtc.time_s[-1] == 1799.5
    assert whtc.duration_s == pytest.approx(1800.0)
    assert load_cycle("whsc", dt=0.5).n_steps == 3790
    assert load_cycle("whtc", dt=1.0).n_steps == 1800
    assert load_cycle("WHTC", dt=0.1).n_steps == 18000
    for name in ("time_s", "engine_speed_rpm", "engine_torque_nm", "engine_power_kw", "exhaust_mass_flow_kg_s",
                 "exhaust_flow_mol_s", "scr_inlet_temperature_k", "nox_ppm", "no2_fraction"):
        arr = getattr(whtc, name)
        assert arr.dtype == np.float64 and arr.shape == (3600,), name
        assert np.all(np.isfinite(arr)), name


def test_interpolation_between_1hz_points(whtc):
    one_hz = load_cycle("whtc", dt=1.0)
    np.testing.assert_allclose(whtc.engine_speed_rpm[::2], one_hz.engine_speed_rpm)
    np.testing.assert_allclose(whtc.engine_torque_nm[::2], one_hz.engine_torque_nm)
    mid = 0.5 * (one_hz.engine_speed_rpm[:-1] + one_hz.engine_speed_rpm[1:])
    np.testing.assert_allclose(whtc.engine_speed_rpm[1:-1:2], mid)
    assert whtc.engine_speed_rpm[-1] == one_hz.engine_speed_rpm[-1]  # last value held
    # row t = 1 s of the table is t = 0: the WHTC starts at idle
    assert whtc.engine_speed_rpm[0] == pytest.approx(ENGINE.idle_speed_rpm)


def test_denormalise():
    speed, torque = denormalise([0.0, 100.0, 50.0, 50.0], [0.0, 100.0, 50.0, np.nan], [False, False, False, True])
    span = 0.45 * 815 + 0.45 * 1418 + 0.1 * 2301 - 500
    assert speed[0] == pytest.approx(500.0)
    assert speed[1] == pytest.approx(span * 2.0327 + 500.0)  # ~1994 rpm
    assert torque[1] == pytest.approx(full_load_torque_nm(ENGINE, speed[1]))
    assert torque[2] == pytest.approx(0.5 * full_load_torque_nm(ENGINE, speed[2]))
    assert torque[3] == pytest.approx(motoring_torque_nm(ENGINE, speed[3])) and torque[3] < 0.0
    with pytest.raises(ValueError, match="t_norm_pct"):
        denormalise([10.0], [np.nan], [False])
    with pytest.raises(ValueError, match="same shape"):
        denormalise([10.0, 20.0], [1.0], [False])


# -------------------------------------------------------------------------------------------- physical ranges
def test_whtc_hot_ranges_like_the_thesis_data(whtc):
    flow = whtc.exhaust_flow_mol_s
    assert 1.3 <= flow.min() <= 1.8  # idle, 500 rpm
    assert 15.0 <= flow.max() <= 18.5  # WHTC touches rated power (0.516 kg/s = 17.9 mol/s)
    assert 3.5 <= flow.mean() <= 6.5 and 8.0 <= np.percentile(flow, 95) <= 14.0
    temp = whtc.scr_inlet_temperature_k
    assert 450.0 <= temp.min() <= 520.0 and 620.0 <= temp.max() <= 710.0
    assert 520.0 <= temp.mean() <= 600.0  # thesis: 534 K mean, 48 K SD
    assert 35.0 <= temp.std() <= 80.0
    nox = whtc.nox_ppm
    assert 1800.0 <= nox.max() <= 2600.0 and nox.min() >= 0.0
    assert 400.0 <= nox.mean() <= 750.0  # thesis: 619 ppm mean, 482 ppm SD
    assert np.all((whtc.no2_fraction >= 0.0) & (whtc.no2_fraction <= 0.5 + 1e-9))
    assert 0.2 <= np.median(whtc.no2_fraction) <= 0.5
    # motoring segments (401 s of the schedule) give negative power
    assert 0.18 <= np.mean(whtc.engine_power_kw < 0.0) <= 0.28
    assert whtc.engine_power_kw.max() == pytest.approx(331.0, rel=0.03)


def test_positive_work(whtc):
    # Checked by hand: mean positive power 64 kW ~ 19 % of P_max over 1800 s. 32.2 kWh for this engine, inside the
    # 25-35 kWh usually quoted for 12-13 L engines.
    assert 28.0 <= whtc.positive_work_kwh <= 36.0
    manual = np.sum(np.clip(whtc.engine_power_kw, 0.0, None)) * 0.5 / 3600.0
    assert whtc.positive_work_kwh == pytest.approx(manual)
    whsc = load_cycle("whsc")
    assert whsc.positive_work_kwh > whtc.positive_work_kwh  # ~46 kWh, steady high-load modes
    assert np.all(whsc.engine_power_kw >= 0.0)  # no motoring in the WHSC


def test_cold_and_hot_start(whtc, whtc_cold):
    cold = whtc_cold.scr_inlet_temperature_k
    assert cold[0] == pytest.approx(298.15, abs=2.0)
    assert np.all(cold[whtc_cold.time_s < 300.0] < 450.0)  # the first minutes stay cold
    assert np.all(cold <= whtc.scr_inlet_temperature_k + 1e-9)
    hot = whtc.scr_inlet_temperature_k
    assert hot[0] == pytest.approx(ENGINE.hot_start_temperature_k, abs=1.0)
    # the thermal memory fades: both starts agree at the end of the cycle
    assert abs(hot[-1] - cold[-1]) < 5.0
    # the cold-start DOC is not yet active: less NO2 in the first minutes
    first = whtc.time_s < 120.0
    assert whtc_cold.no2_fraction[first].mean() < whtc.no2_fraction[first].mean()
    # cold start changes nothing on the engine side
    np.testing.assert_array_equal(whtc.nox_ppm, whtc_cold.nox_ppm)


# ----------------------------------------------------------------------------------------------------- caching
def test_cached_load_is_fast_and_returns_independent_copies():
    load_cycle("whtc")
    start = time.perf_counter()
    for _ in range(10):
        trace = load_cycle("whtc")
    assert (time.perf_counter() - start) / 10 < 0.05
    trace.nox_ppm[:] = -1.0  # writable, and does not corrupt the cache
    assert load_cycle("whtc").nox_ppm.min() >= 0.0


def test_other_engine_gives_other_trace(whtc):
    small = EngineParams(full_load_torque_nm=tuple(0.5 * t for t in ENGINE.full_load_torque_nm))
    trace = load_cycle("whtc", engine=small)
    assert trace.positive_work_kwh < 0.6 * whtc.positive_work_kwh


# ----------------------------------------------------------------------------------------------- random cycles
def test_random_cycle_deterministic_by_seed():
    a = random_cycle(900.0, seed=7)
    b = random_cycle(900.0, seed=7)
    c = random_cycle(900.0, seed=8)
    for name in ("engine_speed_rpm", "engine_torque_nm", "scr_inlet_temperature_k", "nox_ppm", "no2_fraction"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.engine_speed_rpm, c.engine_speed_rpm)
    assert a.n_steps == 1800 and a.name == "random-7"
    d = load_cycle("random", seed=7, duration_s=900.0)
    np.testing.assert_array_equal(a.nox_ppm, d.nox_ppm)
    assert random_cycle(100.0, seed=1, dt=0.3).n_steps == 333


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_random_cycle_is_realistic(seed):
    tr = random_cycle(1800.0, seed=seed)
    assert tr.n_steps == 3600
    assert np.all(np.isfinite(tr.scr_inlet_temperature_k))
    assert 1.3 <= tr.exhaust_flow_mol_s.min() and tr.exhaust_flow_mol_s.max() <= 19.0
    assert 440.0 <= tr.scr_inlet_temperature_k.min() and tr.scr_inlet_temperature_k.max() <= 760.0
    assert tr.nox_ppm.max() <= 2600.0
    assert 0.03 <= np.mean(tr.engine_power_kw < 0.0) <= 0.40  # motoring present
    assert np.mean(tr.engine_speed_rpm < ENGINE.idle_speed_rpm + 10.0) > 0.02  # idle present
    assert 15.0 <= tr.positive_work_kwh <= 60.0
    # rate limited: speed changes at most 8 %/s of the normalised span (~12 rpm per 0.5 s step per %)
    span = (0.45 * 815 + 0.45 * 1418 + 0.1 * 2301 - 500) * 2.0327
    assert np.abs(np.diff(tr.engine_speed_rpm)).max() <= 0.08 * span * 0.5 + 1e-6


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ramped_mode_cycle_is_whsc_like(seed):
    """kind="ramped_modes": an idle start, then loaded steady modes joined by 20 s ramps, no motoring; hot for most
    of the time like the WHSC, and a different trace from the transient generator of the same seed."""
    tr = random_cycle(1800.0, seed=seed, kind="ramped_modes")
    whsc = load_cycle("whsc")
    assert tr.name == f"random-modes-{seed}" and tr.n_steps == 3600
    assert np.all(tr.engine_power_kw >= 0.0)  # no motoring
    assert tr.engine_speed_rpm[0] == pytest.approx(ENGINE.idle_speed_rpm)  # idle start
    assert 0.6 <= np.mean(tr.scr_inlet_temperature_k > 573.15) <= 0.95
    assert tr.scr_inlet_temperature_k.max() <= 800.0 and tr.nox_ppm.max() <= 2600.0
    assert 0.5 * whsc.positive_work_kwh <= tr.positive_work_kwh <= 2.5 * whsc.positive_work_kwh
    # steady modes: most 1 s steps hold the operating point exactly (ramps and the rate limit are the rest)
    speed_1hz = tr.engine_speed_rpm[::2]
    assert np.mean(np.diff(speed_1hz) == 0.0) > 0.7
    assert not np.array_equal(tr.engine_speed_rpm, random_cycle(1800.0, seed=seed).engine_speed_rpm)
    again = random_cycle(1800.0, seed=seed, kind="ramped_modes")
    np.testing.assert_array_equal(tr.scr_inlet_temperature_k, again.scr_inlet_temperature_k)


def test_random_cycle_needs_valid_arguments():
    with pytest.raises(ValueError, match="kind"):
        random_cycle(100.0, seed=1, kind="whsc")
    with pytest.raises(ValueError, match="seed"):
        load_cycle("random")
    with pytest.raises(ValueError, match="seed"):
        random_cycle(100.0, seed=-1)
    with pytest.raises(ValueError, match="duration_s"):
        random_cycle(float("nan"), seed=1)
    with pytest.raises(ValueError, match="duration_s"):
        random_cycle(0.1, seed=1)


# ------------------------------------------------------------------------------------------------ input errors
def test_unknown_cycle_lists_valid_names():
    with pytest.raises(ValueError, match="whtc, whsc, random"):
        load_cycle("ftp75")
    with pytest.raises(ValueError, match="cycle"):
        load_cycle(42)  # type: ignore[arg-type]


@pytest.mark.parametrize("dt", [0.0, -0.5, float("nan"), float("inf"), 11.0, "fast"])
def test_bad_dt(dt):
    with pytest.raises(ValueError, match="dt"):
        load_cycle("whtc", dt=dt)  # type: ignore[arg-type]


# -------------------------------------------------------------------------------------------------------- CSV
def test_csv_round_trip(tmp_path, whtc):
    path = tmp_path / "whtc_copy.csv"
    whtc.to_csv(path)
    back = from_csv(path, dt=0.5)
    assert back.name == "whtc_copy" and back.n_steps == whtc.n_steps
    for name in ("time_s", "engine_speed_rpm", "engine_torque_nm", "engine_power_kw", "exhaust_mass_flow_kg_s",
                 "exhaust_flow_mol_s", "scr_inlet_temperature_k", "nox_ppm", "no2_fraction"):
        np.testing.assert_allclose(getattr(back, name), getattr(whtc, name), rtol=1e-12, atol=1e-12, err_msg=name)
    assert back.positive_work_kwh == pytest.approx(whtc.positive_work_kwh)
    via_load = load_cycle(str(path), dt=0.5)
    np.testing.assert_array_equal(via_load.nox_ppm, back.nox_ppm)
    assert load_cycle(path, dt=1.0).n_steps == 1800


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_csv_minimal_columns_defaults_and_resampling(tmp_path):
    path = _write(tmp_path / "truck.csv", "# measured on a truck\n# second comment\n"
                  "time_s,exhaust_mass_flow_kg_s,scr_inlet_temperature_k,nox_ppm,comment_col\n"
                  "10,0.1,500,100,1\n11,0.2,510,300,1\n12,0.2,520,300,1\n")
    tr = from_csv(path, dt=0.5)
    assert tr.n_steps == 5  # t = 0, 0.5, 1.0, 1.5, 2.0
    np.testing.assert_allclose(tr.time_s, [0.0, 0.5, 1.0, 1.5, 2.0])
    np.testing.assert_allclose(tr.nox_ppm, [100.0, 200.0, 300.0, 300.0, 300.0])
    np.testing.assert_allclose(tr.exhaust_flow_mol_s, tr.exhaust_mass_flow_kg_s / 0.0289)
    np.testing.assert_allclose(tr.no2_fraction, 0.3)
    assert tr.positive_work_kwh == 0.0  # no engine power column: g/kWh unavailable
    assert np.all(tr.engine_speed_rpm == 0.0)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("time_s,scr_inlet_temperature_k\n0,500\n1,500\n", "nox_ppm.*exhaust_flow_mol_s"),
        ("time_s,exhaust_flow_mol_s,scr_inlet_temperature_k,nox_ppm\n0,3,500,\n1,3,500,100\n", "nox_ppm.*NaN"),
        ("time_s,exhaust_flow_mol_s,scr_inlet_temperature_k,nox_ppm\n0,3,500,nan\n1,3,500,100\n", "nox_ppm"),
        ("time_s,exhaust_flow_mol_s,scr_inlet_temperature_k,nox_ppm\n0,-3,500,1\n1,3,500,100\n",
         "exhaust_flow_mol_s"),
        ("time_s,exhaust_flow_mol_s,scr_inlet_temperature_k,nox_ppm\n0,3,500,1\n0,3,500,100\n", "time_s"),
        ("time_s,exhaust_flow_mol_s,scr_inlet_temperature_k,nox_ppm,no2_fraction\n0,3,500,1,1.5\n1,3,500,1,0.2\n",
         "no2_fraction"),
        ("time_s,exhaust_flow_mol_s,scr_inlet_temperature_k,nox_ppm\n0,3,-5,1\n1,3,500,100\n",
         "scr_inlet_temperature_k"),
        ("time_s,exhaust_flow_mol_s,scr_inlet_temperature_k,nox_ppm\n0,3,500,1\n", "two data rows"),
        ("time_s,exhaust_flow_mol_s,scr_inlet_temperature_k,nox_ppm\n0,3,500\n1,3,500,100\n", "fields"),
        ("time_s,exhaust_flow_mol_s,scr_inlet_temperature_k,nox_ppm\n0,3,warm,1\n1,3,500,100\n", "not numeric"),
        ("# only a comment\n", "header"),
    ],
)
def test_csv_errors(tmp_path, text, match):
    path = _write(tmp_path / "bad.csv", text)
    with pytest.raises(ValueError, match=match):
        from_csv(path)


def test_csv_missing_file_and_bad_dt(tmp_path):
    with pytest.raises(ValueError, match="path"):
        from_csv(tmp_path / "nope.csv")
    with pytest.raises(ValueError, match="cycle"):
        load_cycle(str(tmp_path / "nope.csv"))
    good = _write(tmp_path / "ok.csv", "time_s,exhaust_flow_mol_s,scr_inlet_temperature_k,nox_ppm\n0,3,500,1\n"
                  "1,3,500,100\n")
    with pytest.raises(ValueError, match="dt"):
        from_csv(good, dt=0.0)


def test_exhaust_trace_validates_lengths():
    ones = np.ones(3)
    with pytest.raises(ValueError, match="nox_ppm"):
        ExhaustTrace(name="x", dt=1.0, time_s=ones, engine_speed_rpm=ones, engine_torque_nm=ones,
                     engine_power_kw=ones, exhaust_mass_flow_kg_s=ones, exhaust_flow_mol_s=ones,
                     scr_inlet_temperature_k=ones, nox_ppm=np.ones(2), no2_fraction=ones)


# -------------------------------------------------------------------------------------- temperature unit checks
_HEADER = "time_s,exhaust_flow_mol_s,scr_inlet_temperature_k,nox_ppm\n"


def _temperature_csv(tmp_path, temps) -> Path:
    rows = "".join(f"{i},5,{t},300\n" for i, t in enumerate(temps))
    return _write(tmp_path / "temps.csv", _HEADER + rows)


def test_csv_temperatures_in_degc_are_rejected(tmp_path):
    """A cycle in degC (here a cold start: 20 degC rising to 350 degC) read as kelvin would be 20 K: impossible."""
    path = _temperature_csv(tmp_path, [20, 80, 150, 250, 350])
    with pytest.raises(ValueError, match=r"scr_inlet_temperature_k goes down to 20 K.*degC.*T\[K\] = T\[degC\] \+ "
                                         r"273\.15"):
        from_csv(path)
    with pytest.raises(ValueError, match="scr_inlet_temperature_k"):
        load_cycle(path)


def test_csv_cycle_below_freezing_throughout_warns_but_loads(tmp_path):
    """All values in 200-273 K: probably degC of a hot cycle (250 degC), possibly a sub-zero cold-start segment."""
    path = _temperature_csv(tmp_path, [250, 255, 260])
    with pytest.warns(UserWarning, match=r"scr_inlet_temperature_k never reaches 273.15 K.*degC"):
        tr = from_csv(path, dt=1.0)
    np.testing.assert_array_equal(tr.scr_inlet_temperature_k, [250.0, 255.0, 260.0])


def test_csv_arctic_cold_start_in_kelvin_is_accepted_silently(tmp_path):
    import warnings

    path = _temperature_csv(tmp_path, [205.0, 230.0, 280.0, 400.0, 520.0])  # -68 degC ambient, warming up
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tr = from_csv(path, dt=1.0)
    assert tr.scr_inlet_temperature_k[0] == 205.0


def test_shipped_cycles_pass_the_temperature_unit_checks(tmp_path):
    import warnings

    for cycle in ("whtc", "whsc"):
        for cold in (False, True):
            path = tmp_path / f"{cycle}_{cold}.csv"
            load_cycle(cycle, cold_start=cold).to_csv(path)
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                from_csv(path)


@pytest.mark.parametrize("value", ["no", "False", 1, 0, None])
def test_cold_start_must_be_a_bool(value):
    with pytest.raises(ValueError, match=r"^cold_start must be True or False"):
        load_cycle("whtc", cold_start=value)
    with pytest.raises(ValueError, match=r"^cold_start must be True or False"):
        random_cycle(60.0, seed=1, cold_start=value)


def test_cold_start_accepts_numpy_bools():
    np.testing.assert_array_equal(load_cycle("whtc", cold_start=np.True_).scr_inlet_temperature_k,
                                  load_cycle("whtc", cold_start=True).scr_inlet_temperature_k)
