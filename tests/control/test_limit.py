"""The clairvoyant optimum (control.limit): the NLP is the environment's plant and KPIs, its optimum replays within
1 % through the environment, the front is monotone, the stored limit matches the current plant."""
from __future__ import annotations

import itertools
import json
import math
import warnings

import numpy as np
import pytest

from control import limit as L
from control.limit.stored import _signature, _source_digest

#: a short, warm piece of the hot WHTC (2 minutes at 0.5 s, 300-390 C at the SCR inlet)
SEGMENT = (2800, 240)


@pytest.fixture(scope="module")
def segment():
    return L.cycle_segment("whtc", *SEGMENT)


@pytest.fixture(scope="module")
def problem(segment):
    return L.CycleOptimum(segment, jit=False, reduced_iterations=(150, 80))


@pytest.fixture(scope="module")
def front(problem):
    return L.pareto_front(problem, (2.0, 5.0), first_ppm=5.0)


# --------------------------------------------------------------------------------------- the NLP is the plant
def test_objective_weights_are_the_environments_kpis(problem, segment):
    """The NLP's sums (weights from the environment's own KPI accounting, states from the plant kernel) equal the
    environment's episode KPIs for any dose."""
    dose = problem.lookup_table_dose() * 1.3
    _, nox, nh3 = problem.simulate(dose)
    kpis = L.replay(segment, dose)
    assert nox @ problem.nox_weight == pytest.approx(kpis["tailpipe_nox_g_per_kwh"], rel=1e-12)
    assert nh3 @ problem.slip_weight == pytest.approx(kpis["mean_nh3_slip_ppm"], rel=1e-12)
    assert problem.engine_work_kwh == pytest.approx(kpis["engine_work_kwh"], rel=1e-12)


@pytest.mark.parametrize("plant", [None, ({"age_h": 8.0}, 0), ({"randomize": 0.2}, 101)],
                         ids=["fresh", "aged_8h", "randomised_seed_101"])
def test_the_twins_implicit_step_holds_on_the_kernels_trajectory(problem, segment, plant):
    """The NLP's equality constraints are satisfied by the plant's own trajectory (to the kernel's Newton
    tolerance), and its outputs are the plant's: for the fresh catalyst, an aged one and the catalyst an episode
    draws at reset with domain randomisation (the RL benchmark's Aged and Randomised tasks)."""
    if plant is not None:
        problem = L.CycleOptimum(segment, env_kwargs=plant[0], seed=plant[1], jit=False)
        fresh = L.make_env(segment)
        fresh.reset(seed=0)
        assert not np.array_equal(problem._cat[0], fresh.catalyst_params_array)
    dose = problem.lookup_table_dose()
    cov, nox, nh3 = problem.simulate(dose)
    x = np.r_[cov.ravel(), problem.held(dose)]
    import casadi as ca

    g = np.asarray(ca.Function("g", [problem._nlp["x"], problem._nlp["p"]], [problem._nlp["g"]])(x, problem._p)).ravel()
    n = problem.n_cells * problem.n_steps
    assert np.max(np.abs(g[:n])) < 1e-9
    nox_nlp, nh3_nlp, _ = (np.asarray(v).ravel() for v in problem._outputs(x, problem._p))
    np.testing.assert_allclose(nox_nlp, nox, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(nh3_nlp, nh3, rtol=1e-5, atol=1e-6)


def test_adjoint_gradient_matches_finite_differences(problem):
    doses = problem.held(problem.lookup_table_dose())
    c = problem._reduced(doses, True)
    grad = c["gradient"].copy()
    direction = np.random.default_rng(0).standard_normal(doses.size) * 0.01
    eps = 1e-4
    up, down = np.clip(doses + eps * direction, 0, 3), np.clip(doses - eps * direction, 0, 3)
    fu, fd = problem._reduced(up, False), problem._reduced(down, False)
    for i, key in enumerate(("nox", "slip")):
        assert grad[:, i] @ (up - down) == pytest.approx(fu[key] - fd[key], rel=1e-4)


# ------------------------------------------------------------------------------------------------ the optimum
def test_optimum_replays_through_the_environment_within_1_percent(front, segment):
    for budget, r in front.items():
        assert r.success, r.status
        assert r.replay_error < 0.01
        assert r.replay_mean_nh3_slip_ppm == pytest.approx(r.mean_nh3_slip_ppm, rel=0.01, abs=0.01)
        assert r.replay_mean_nh3_slip_ppm <= budget * 1.01
        kpis = L.replay(segment, r.dose_g_s)
        assert kpis["tailpipe_nox_g_per_kwh"] == pytest.approx(r.replay_tailpipe_nox_g_per_kwh, rel=1e-12)
        assert np.all((r.dose_g_s >= 0) & (r.dose_g_s <= 3.0))


def test_optimum_beats_the_look_up_table_and_a_larger_budget_never_costs_nox(front, problem, segment):
    lut = L.replay(segment, problem.lookup_table_dose())
    feasible = [r for b, r in front.items() if lut["mean_nh3_slip_ppm"] <= b]
    for r in feasible:
        assert r.replay_tailpipe_nox_g_per_kwh <= lut["tailpipe_nox_g_per_kwh"]
    assert front[5.0].tailpipe_nox_g_per_kwh <= front[2.0].tailpipe_nox_g_per_kwh * (1 + 1e-6)
    # a perturbed optimum within the budget is no better (a local optimum, checked along random directions)
    r = front[5.0]
    rng = np.random.default_rng(1)
    for _ in range(3):
        dose = np.clip(r.dose_g_s + rng.normal(0.0, 0.02, r.dose_g_s.size), 0.0, 3.0)
        k = L.replay(segment, dose)
        if k["mean_nh3_slip_ppm"] <= 5.0:
            assert k["tailpipe_nox_g_per_kwh"] >= r.replay_tailpipe_nox_g_per_kwh * (1 - 1e-6)


def test_primal_dual_warm_start_and_peak_bound(segment, front):
    peaked = L.CycleOptimum(segment, jit=False, peak_ppm=15.0, reduced_iterations=(0, 0))
    r = peaked.solve(5.0, warm_start=front[5.0].dose_g_s)
    assert r.success, r.status
    assert r.peak_nh3_slip_ppm <= 15.0 * (1 + 1e-6)
    assert r.replay["peak_nh3_slip_ppm"] <= 15.0 * 1.01
    assert r.tailpipe_nox_g_per_kwh >= front[5.0].tailpipe_nox_g_per_kwh * (1 - 1e-4)
    with pytest.raises(ValueError, match="peak_ppm"):
        L.CycleOptimum(segment, jit=False).solve(5.0, peak_ppm=10.0)


def test_bad_arguments_are_refused(segment, problem):
    for bad in ("sensor_noise", "actuator", "action_mode"):
        with pytest.raises(ValueError, match=bad):
            L.CycleOptimum(segment, env_kwargs={bad: False})
    with pytest.raises(ValueError, match="seed"):
        L.CycleOptimum(segment, seed=-1)
    with pytest.raises(ValueError, match="hold_steps"):
        L.CycleOptimum(segment, hold_steps=0)
    with pytest.raises(ValueError, match="budget_ppm"):
        problem.solve(-1.0)
    with pytest.raises(ValueError, match="warm_start"):
        problem.solve(5.0, warm_start=np.zeros(3))
    with pytest.raises(ValueError, match="past the end"):
        L.cycle_segment("whtc", 3500, 200)
    with pytest.raises(ValueError, match="dose_g_s"):
        L.replay(segment, np.zeros(5))


# ---------------------------------------------------------------------------------------------- gap to limit
def test_gap_to_limit():
    assert L.gap_to_limit(0.6, 0.6, 0.1) == 0.0
    assert L.gap_to_limit(0.6, 0.1, 0.1) == 1.0
    assert L.gap_to_limit(0.6, 0.35, 0.1) == pytest.approx(0.5)
    assert L.gap_to_limit(0.6, 0.8, 0.1) < 0
    assert math.isnan(L.gap_to_limit(0.1, 0.2, 0.1))
    for bad in (float("nan"), float("inf"), "0.3", None, True):
        with pytest.raises(ValueError, match="controller_nox"):
            L.gap_to_limit(0.6, bad, 0.1)


# ------------------------------------------------------------------------------------------- stored results
def test_stored_limit_is_complete_and_consistent():
    doc = L.stored_limits()
    assert doc["command"].startswith("python -m experiments.limit")
    for cycle in L.STORED_CYCLES:
        budgets = doc["cycles"][cycle]["budgets"]
        assert sorted(budgets, key=float) == ["1", "2", "5", "10", "20"]
        nox = [budgets[k]["tailpipe_nox_g_per_kwh"] for k in ("1", "2", "5", "10", "20")]
        assert all(b <= a * 1.01 for a, b in itertools.pairwise(nox))
        for key, rec in budgets.items():
            assert rec["replay_relative_error"] < 0.01
            assert rec["replay_mean_nh3_slip_ppm"] <= float(key) * 1.01
            r = L.stored_limit(cycle, float(key), check_plant=False)
            assert r.dose_g_s.size == doc["cycles"][cycle]["n_steps"]
        lut = doc["cycles"][cycle]["lookup_table"]
        assert budgets["10"]["replay_tailpipe_nox_g_per_kwh"] < lut["tailpipe_nox_g_per_kwh"]


def test_stored_limit_matches_the_current_plant():
    """Fails when the plant changed since the limit was stored (the phys stream's chemistry, the cycles, the
    kernel): re-solve with `python -m experiments.limit --store`."""
    doc = L.stored_limits()
    for name, entry in doc["cycles"].items():  # the two cycles and any other plant stored (the RL tasks')
        cycle, kw, seed = entry.get("cycle", name), entry.get("env_kwargs") or {}, entry.get("seed", 0)
        stored = entry["fingerprint"]
        now = L.plant_fingerprint(cycle, kw, seed)
        changed = L.fingerprint_changes(stored, now)
        assert not changed, (f"the stored limit of {name} was solved for another plant ({', '.join(changed)} "
                             "changed): re-solve with `python -m experiments.limit --store`")
        for key in entry["budgets"]:
            r = L.stored_limit(name, float(key), check_plant=False)
            assert r.replay_error < 0.01 and r.replay_mean_nh3_slip_ppm <= float(key) * 1.01
            kpis = L.replay(cycle, r.dose_g_s, kw, seed=seed)
            assert kpis["tailpipe_nox_g_per_kwh"] == pytest.approx(r.replay_tailpipe_nox_g_per_kwh, rel=1e-6), (
                f"{name}@{key} ppm: the stored dose no longer gives the stored NOx: re-solve the limit")
            assert kpis["mean_nh3_slip_ppm"] == pytest.approx(r.replay_mean_nh3_slip_ppm, rel=1e-6, abs=1e-9)


def _limit_document(tmp_path, result, fingerprint, name="limit.json"):
    doc = {"command": "python -m experiments.limit --segment", "cycles": {"whtc": {
        "fingerprint": fingerprint, "budgets": {"5": result.to_dict()}}}}
    return L.write_limit_document(doc, tmp_path / name)


def test_stored_limit_reads_a_document_and_warns_when_the_plant_changed(tmp_path, front):
    """stored_limit answers from the file (never re-solves), compares the stored plant fingerprint with the current
    plant's and warns (StaleLimitWarning, naming what changed) when they differ."""
    now = L.plant_fingerprint("whtc")
    path = _limit_document(tmp_path, front[5.0], now)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rec = L.stored_limit("whtc", 5, path=path)
    assert rec.replay_tailpipe_nox_g_per_kwh == front[5.0].replay_tailpipe_nox_g_per_kwh
    np.testing.assert_allclose(rec.dose_g_s, front[5.0].dose_g_s, atol=1e-7)
    # the record as control_benchmark reads it: by key, or as one number (the replayed NOx)
    assert rec["tailpipe_nox_g_per_kwh"] == front[5.0].tailpipe_nox_g_per_kwh
    assert float(rec) == rec["replay_tailpipe_nox_g_per_kwh"] == rec.replay_tailpipe_nox_g_per_kwh
    with pytest.raises(KeyError, match="not an entry"):
        rec["nox"]
    for part in ("chemistry", "catalyst"):
        stale = _limit_document(tmp_path, front[5.0], {**now, part: "0" * 16}, f"stale_{part}.json")
        with pytest.warns(L.StaleLimitWarning, match=part):
            L.stored_limit("whtc", 5, path=stale)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            L.stored_limit("whtc", 5, path=stale, check_plant=False)
    aged = _limit_document(tmp_path, front[5.0], L.plant_fingerprint("whtc", {"age_h": 8.0}), "aged.json")
    with pytest.warns(L.StaleLimitWarning, match="catalyst"):
        L.stored_limit("whtc", 5, path=aged)


def test_stored_limit_of_another_plant_is_found_by_its_fingerprint(tmp_path, front):
    """The RL benchmark's plants (an aged catalyst, the catalyst an episode draws at reset) are stored entries of
    their own, found by the plant's fingerprint, never by a guessed name."""
    assert L.plant_entry_name("whtc") == "whtc"
    assert L.plant_entry_name("whtc", {"age_h": 4.0}) == "whtc@age_h=4"
    assert L.plant_entry_name("whtc", {"randomize": 0.2}, 101) == "whtc@randomize=0.2,seed=101"
    plants = {"whtc@age_h=8": ({"age_h": 8.0}, 0), "whtc@randomize=0.2,seed=101": ({"randomize": 0.2}, 101)}
    doc = {"command": "python -m experiments.limit", "cycles": {"whtc": {
        "fingerprint": L.plant_fingerprint("whtc"), "budgets": {"5": front[2.0].to_dict()}}}}
    for name, (kw, seed) in plants.items():
        doc["cycles"][name] = {"cycle": "whtc", "env_kwargs": kw, "seed": seed, "budgets": {"5": front[5.0].to_dict()},
                               "fingerprint": L.plant_fingerprint("whtc", kw, seed)}
    path = L.write_limit_document(doc, tmp_path / "plants.json")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name, (kw, seed) in plants.items():
            rec = L.stored_limit("whtc", 5, env_kwargs=kw, seed=seed, path=path)
            assert rec.cycle == name and float(rec) == front[5.0].replay_tailpipe_nox_g_per_kwh
            assert L.stored_limit(name, 5, path=path).cycle == name
        assert float(L.stored_limit("whtc", 5, path=path)) == front[2.0].replay_tailpipe_nox_g_per_kwh
    with pytest.raises(ValueError, match="no stored limit for the plant whtc@age_h=4.*CycleOptimum"):
        L.stored_limit("whtc", 5, env_kwargs={"age_h": 4.0}, path=path)
    with pytest.raises(ValueError, match="no stored limit for the plant whtc@randomize=0.2,seed=102"):
        L.stored_limit("whtc", 5, env_kwargs={"randomize": 0.2}, seed=102, path=path)


def test_stored_limit_errors_name_the_cycle_budget_or_file(tmp_path, front):
    path = _limit_document(tmp_path, front[5.0], {})
    with pytest.raises(ValueError, match="cycle 'nedc'.*stored: whtc"):
        L.stored_limit("nedc", path=path, check_plant=False)
    with pytest.raises(ValueError, match="budget_ppm 3.*stored: 5 ppm"):
        L.stored_limit("whtc", 3, path=path, check_plant=False)
    with pytest.raises(ValueError, match="budget_ppm"):
        L.stored_limit("whtc", -1, path=path, check_plant=False)
    with pytest.raises(FileNotFoundError, match="experiments.limit --store"):
        L.stored_limits(tmp_path / "missing.json")
    for name, text in (("bad.json", "{not json"), ("list.json", "[1, 2]"), ("nocycles.json", '{"budgets": {}}'),
                       ("binary.json", b"\xff\xfe\x00")):
        bad = tmp_path / name
        bad.write_bytes(text if isinstance(text, bytes) else text.encode())
        with pytest.raises(ValueError, match=name.replace(".", r"\.")):
            L.stored_limit("whtc", 10, path=bad)
    broken = tmp_path / "broken.json"
    broken.write_text(json.dumps({"cycles": {"whtc": {"budgets": {"10": {"mean_nh3_slip_ppm": 1.0}}}}}),
                      encoding="utf-8")
    with pytest.raises(ValueError, match="broken.json: the record of whtc at 10 ppm is not a limit record"):
        L.stored_limit("whtc", 10, path=broken, check_plant=False)
    broken.write_text(json.dumps({"cycles": {"whtc": ["not", "an", "entry"]}}), encoding="utf-8")
    with pytest.raises(ValueError, match="broken.json: the entry of whtc"):
        L.stored_limit("whtc", 10, path=broken, check_plant=False)


def test_result_record_round_trip(front):
    r = front[5.0]
    back = L.LimitResult.from_dict(r.cycle, json.loads(json.dumps(r.to_dict())))
    assert back.tailpipe_nox_g_per_kwh == r.tailpipe_nox_g_per_kwh
    assert back.replay_tailpipe_nox_g_per_kwh == r.replay_tailpipe_nox_g_per_kwh
    np.testing.assert_allclose(back.dose_g_s, r.dose_g_s, atol=1e-7)


def test_fingerprint_tracks_the_plant_not_the_comments(tmp_path, monkeypatch):
    base = L.plant_fingerprint("whtc")
    aged = L.plant_fingerprint("whtc", {"ageing": 0.5})
    assert aged["catalyst"] != base["catalyst"] and aged["cycle"] == base["cycle"]
    assert L.plant_fingerprint("whsc")["cycle"] != base["cycle"]
    mod = tmp_path / "chem_a.py"
    mod.write_text('"""doc"""\n\ndef f(x):\n    """doc"""\n    return 2.0 * x  # twice\n', encoding="utf-8")
    monkeypatch.syspath_prepend(str(tmp_path))
    import importlib

    a = importlib.import_module("chem_a")
    digest = _source_digest(a)
    mod.write_text('"""other doc"""\n\ndef f(x):\n    """other"""\n    return 2.0 * x  # reworded\n', encoding="utf-8")
    assert _source_digest(importlib.reload(a)) == digest
    mod.write_text('"""doc"""\n\ndef f(x):\n    """doc"""\n    return 3.0 * x\n', encoding="utf-8")
    assert _source_digest(importlib.reload(a)) != digest


def test_task_limit_metrics_are_the_stored_limit_of_each_episodes_plant():
    """The RL benchmark's reference rows: one per evaluation episode of the task, the stored 10 ppm limit of its plant
    (the WHTC task's episodes share the fresh catalyst's limit; sensor-noise seeds share it)."""
    from scr_env.tasks import get_task

    task = get_task("WHTC")
    rows = L.task_limit_metrics(task)
    assert len(rows) == task.protocol.n_episodes
    want = L.stored_limit("whtc", 10.0, check_plant=False)
    for row in rows:
        assert set(row) == {"condition", "seed", "kpis", "wall_time_s"}
        assert row["kpis"]["tailpipe_nox_g_per_kwh"] == float(want)
        assert row["kpis"]["mean_nh3_slip_ppm"] <= 10.0 * 1.01
        assert row["kpis"]["command_total_variation_g_s_per_h"] >= 0.0


def test_fingerprint_ignores_last_bits_and_sees_real_changes():
    """A numeric signature is immune to a last-bit change of any value (a numpy release or CPU; version 1's
    rounded-float hash flipped on values such as 0.4960853952865, a rounding tie at 12 digits) and sees a change
    of one value in a long series, of a small parameter beside large ones, and of the series' length."""
    rng = np.random.default_rng(0)
    drive = rng.uniform(0.1, 900.0, (3600, 5))
    drive[17, 2] = 0.4960853952865
    params = {"a_ox_no": 1.37e10, "o2_order_ox": 0.60314, "n_cells": 5.0}
    base = {"cycle": _signature({"drive": drive, "dt": 0.5}), "catalyst": _signature(params),
            "chemistry": "abc", "version": 2}

    def changes(drive2, params2, chem="abc"):
        now = {"cycle": _signature({"drive": drive2, "dt": 0.5}), "catalyst": _signature(params2),
               "chemistry": chem, "version": 2}
        return L.fingerprint_changes(json.loads(json.dumps(base)), now)  # stored as JSON, as in the package

    ulp = drive.copy()
    ulp[17, 2] = np.nextafter(ulp[17, 2], 1.0)
    ulp[::7] = np.nextafter(ulp[::7], np.inf)
    assert changes(ulp, {**params, "a_ox_no": np.nextafter(1.37e10, 0.0)}) == []
    one = drive.copy()
    one[1234, 3] *= 1 + 1e-5
    assert changes(one, params) == ["cycle"]
    assert changes(drive, {**params, "o2_order_ox": 0.60315}) == ["catalyst"]
    assert changes(drive[:-1], params) == ["cycle"]
    assert changes(drive, params, chem="abd") == ["chemistry"]
    assert L.fingerprint_changes({**base, "version": 1}, base) == ["catalyst", "chemistry", "cycle"]


def test_annotate_gap_to_limit_writes_every_row():
    """The benchmarks' gap_to_limit: from the look-up-table row to the stored limit, in every row; None where the
    cycle has no stored limit."""
    rows = {"lookup_table": {"tailpipe_nox_g_per_kwh": 0.7}, "x": {"tailpipe_nox_g_per_kwh": 0.3}}
    lim = L.annotate_gap_to_limit(rows, "whtc")
    assert lim == pytest.approx(L.limit_nox("whtc")) and rows["lookup_table"]["gap_to_limit"] == 0.0
    assert rows["x"]["gap_to_limit"] == pytest.approx((0.7 - 0.3) / (0.7 - lim))
    none = {"lookup_table": {"tailpipe_nox_g_per_kwh": 0.7}}
    assert L.annotate_gap_to_limit(none, "whtc_0-600s") is None and none["lookup_table"]["gap_to_limit"] is None
