"""control.loop (the identify-then-control loop): the gap-closed measure respects the slip limit; held-out segments;
the output stack."""
from __future__ import annotations

import casadi as ca
import numpy as np

from control.loop import SLIP_LIMIT_PPM, gap_closed, held_out
from ident.linear import ARX
from ident.stack import OutputStack


def _row(g_per_kwh: float, slip: float) -> dict[str, float]:
    return {"tailpipe_nox_g_per_kwh": g_per_kwh, "mean_nh3_slip_ppm": slip}


def test_gap_closed_counts_only_controllers_within_the_slip_limit() -> None:
    kpis = {"whtc": {"lookup_table": _row(0.6, 7.0), "mpc_oracle": _row(0.4, 1.0), "mpc_a": _row(0.45, 3.0),
                     "mpc_b": _row(0.2, SLIP_LIMIT_PPM + 5.0)}}
    gaps, excluded = gap_closed(kpis)
    assert abs(gaps["a"]["whtc"] - 0.75) < 1e-12
    assert "b" not in gaps
    assert excluded[0]["model"] == "b" and abs(excluded[0]["raw_fraction"] - 2.0) < 1e-12


def test_gap_closed_needs_an_oracle_within_the_limit() -> None:
    kpis = {"whtc": {"lookup_table": _row(0.6, 7.0), "mpc_oracle": _row(0.4, 50.0), "mpc_a": _row(0.45, 3.0)}}
    gaps, excluded = gap_closed(kpis)
    assert gaps == {} and excluded[0]["reason"].startswith("oracle")


def test_quick_held_out_is_the_start_of_the_whtc() -> None:
    (trace,) = held_out(quick=True)
    assert trace.n_steps == 1200 and trace.name.startswith("whtc")
    full = held_out(quick=False)
    assert [t.name for t in full] == ["whtc", "whsc"]
    np.testing.assert_array_equal(trace.nox_ppm, full[0].nox_ppm[:1200])


def test_output_stack_predicts_and_exports_like_its_parts() -> None:
    rng = np.random.default_rng(0)
    u = rng.standard_normal((400, 2))
    y = np.column_stack([np.convolve(u[:, 0], [0.5, 0.3], "full")[:400],
                         np.convolve(u[:, 1], [0.2, 0.1], "full")[:400]])
    stack = OutputStack([ARX(na=1, nb=2, nk=0), ARX(na=1, nb=2, nk=0)]).fit(u, y)
    yp = stack.predict(u)
    assert yp.shape == (400, 2)
    f = stack.to_casadi()
    x = np.zeros(int(f.size1_in(0)))
    ys = []
    for t in range(400):
        x, yt = f(x, u[t])
        ys.append(np.asarray(yt).ravel())
    np.testing.assert_allclose(np.array(ys), yp, atol=1e-8)
    assert isinstance(f, ca.Function)


def test_loop_report_shows_kpis_gaps_limit_and_the_ablation_legend() -> None:
    from control.loop_report import loop_report

    row = {"tailpipe_nox_g_per_kwh": 0.5, "mean_nh3_slip_ppm": 1.0, "peak_nh3_slip_ppm": 5.0, "nox_conversion": 0.9,
           "adblue_g": 100.0, "solve_time_ms_median": 10.0, "solve_time_ms_p95": 20.0, "solver_failures": 0.0}
    kfit = {"40_steps": [[50.0, 60.0]], "160_steps": [[30.0, 40.0]]}
    doc = {"quick": False, "seeds": [0, 1], "wall_time_s": 12.0, "oracle": "the oracle", "ablation": True,
           "identification": {"greybox": {"validation_fit_percent_whtc": {"nox": 80.0}},
                              "black_box": {"models": {"rpem": {"validation_kstep_fit_percent": kfit,
                                                                "fit_seconds": 3.0},
                                                       "hammerstein_wiener-no_static_blocks": {"error": "boom"}}}},
           "kpis": {"whtc": {"lookup_table": row, "mpc_rpem": {**row, "tailpipe_nox_g_per_kwh": 0.3}}},
           "gap_closed": {"rpem": {"whtc": 0.5}}, "gap_closed_excluded": [],
           "gap_to_limit": {"whtc": {"limit_tailpipe_nox_g_per_kwh": 0.05,
                                     "controllers": {"mpc_rpem": {"gap_to_limit": 0.44, "within_slip_limit": True}}}}}
    text = loop_report(doc, [])
    assert "| rpem | 0.50 |" in text and "| mpc_rpem | 0.44 |" in text and "limit 0.050 g/kWh" in text
    assert "linear model class" in text and "failed: boom" in text and "the oracle" in text


def test_sensor_noise_free_controllers_do_not_depend_on_the_noise_seed():
    """The premise of replicate_over_seeds: the oracle's doses and KPIs are bitwise equal under two sensor-noise
    seeds (while no solve fails)."""
    from control.evaluation import evaluate
    from control.loop import SENSOR_NOISE_FREE, loop_controller

    for name in SENSOR_NOISE_FREE:
        runs = [evaluate(loop_controller(name, None, None, quick=True), cycles=("whtc",), seeds=(s,),
                         max_steps=120, record_trajectory=True)[0] for s in (0, 5)]
        assert runs[0].stats["solver_failures"] == 0
        assert np.array_equal(runs[0].trajectory["adblue_g_s"], runs[1].trajectory["adblue_g_s"]), name
        assert runs[0].kpis == runs[1].kpis, name


def _episode(name, seed, cycle="whtc", **kw):
    return {"name": name, "cycle": cycle, "seed": seed, "row": {"seed": seed, "x": float(seed), "solver_failures": 0.0},
            "trajectory": {"t": [0]}, **kw}


def test_replicate_over_seeds_copies_only_the_noise_free_controllers():
    from control.loop import replicate_over_seeds

    rows = [_episode("mpc_oracle", 3), _episode("lookup_table", 3), _episode("lookup_table", 1)]
    out, rerun = replicate_over_seeds(rows, (3, 1, 2))
    assert rerun == []
    oracle = [(r["seed"], r["row"]["seed"], r["row"]["x"], r.get("replicated_from")) for r in out
              if r["name"] == "mpc_oracle"]
    assert oracle == [(3, 3, 3.0, None), (1, 1, 3.0, 3), (2, 2, 3.0, 3)]   # the KPIs of seed 3, the seed relabelled
    assert sorted(r["seed"] for r in out if r["name"] == "lookup_table") == [1, 3]
    assert all(r["trajectory"] == {} for r in out if r.get("replicated_from") is not None)
    assert rows[0]["row"]["seed"] == 3                                          # the original is not touched
    assert replicate_over_seeds(rows, (3,)) == (rows, [])


def test_replicate_over_seeds_reruns_a_first_seed_episode_that_failed_or_fell_back():
    from control.loop import replicate_over_seeds

    failed = _episode("mpc_oracle", 0, "whsc")
    failed["row"]["solver_failures"] = 2.0
    rows = [_episode("mpc_oracle", 0), failed, {"name": "mpc_oracle", "cycle": "whtc", "seed": 0, "error": "x"}]
    out, rerun = replicate_over_seeds(rows[1:], (0, 1))
    assert out == rows[1:] and sorted(rerun) == [("mpc_oracle", "whsc"), ("mpc_oracle", "whtc")]


def test_slowest_first_puts_the_oracle_and_black_box_nmpcs_first_and_keeps_the_order_otherwise():
    from control.loop import slowest_first

    names = ["lookup_table", "mpc_oracle", "mpc_greybox", "mpc_rpem", "mpc_hammerstein_wiener-no_preview", "pi",
             "ppo", "mpc_rpem"]
    order = [t["name"] for t in slowest_first([{"name": n, "i": i} for i, n in enumerate(names)])]
    assert order == ["mpc_oracle", "mpc_rpem", "mpc_hammerstein_wiener-no_preview", "mpc_rpem", "mpc_greybox",
                     "lookup_table", "pi", "ppo"]
