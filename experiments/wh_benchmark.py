"""Paper II, section 5: RPEM on the Wiener-Hammerstein benchmark (Schoukens, Suykens and Ljung, SYSID 2009).

Model: 2nd-order chain, the 8 terms (1, u, x2, x2 u, x1, x1 u, x1 x2, x1 x2 u), alpha = 2500 (T = 1/51200 s),
delta = 0.025, R(0) = 100 I, Lambda(0) = 0.1, x(0) = (y(0), 0), parameters started by the Kalman-filter
initialisation of Brus and Wigren (from theta = 0, Paper III's tuning), then RPEM passes over the estimation data
until the simulation fit stops improving (at most 15 passes). The forgetting factor rises from 0.9999 to 1 at
rate 0.9999: the faster default (0.999) makes the first passes wander into unstable simulations before settling.
State and sensitivity saturations are 20 and 1e3 (the output is within +-1 V).

Split: the benchmark's standard one, samples 1..100000 for estimation and 100001..188000 for test (1-based).

The model is identified twice, with midpoint (Paper II's method) and with Euler discretisation; the reported
model (``selected_method``) is the one with the lower RMS simulation error on the *estimation* data; the test data
play no part in any choice. Both test figures are reported.

Usage: ``python -m experiments.wh_benchmark [--passes 15] [--json PATH]``
"""
from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from importlib import resources

import numpy as np
import scipy.io

from control.plots import pyplot
from experiments._runs import run_folder, save_results, write_figure
from ident.metrics import fit_percent, rms
from ident.rpem import PAPER2_TERMS, RecursivePEM

FS_HZ = 51200.0
N_ESTIMATION = 100_000


def load_benchmark() -> tuple[np.ndarray, np.ndarray]:
    """Input and output voltages [V] of the Wiener-Hammerstein benchmark (188000 samples at 51.2 kHz)."""
    path = resources.files("ident") / "data" / "benchmarks" / "WienerHammerBenchMark.mat"
    with resources.as_file(path) as p:
        data = scipy.io.loadmat(str(p))
    return data["uBenchMark"].ravel().astype(float), data["yBenchMark"].ravel().astype(float)


def estimator(method: str, passes: int) -> RecursivePEM:
    """Paper II's set-up for the benchmark."""
    return RecursivePEM(n_states=2, terms=PAPER2_TERMS, sampling_period=1.0 / FS_HZ, alpha=2500.0, method=method,
                        stability_margin=0.025, theta0=np.zeros(len(PAPER2_TERMS)), R0=100.0, Lambda0=0.1,
                        forgetting_initial=0.9999, forgetting_rate=0.9999, state_bound=20.0,
                        sensitivity_bound=1e3, init="kalman", n_passes=passes)


def plot(y_test: np.ndarray, y_sim: np.ndarray, path, title: str) -> None:
    plt = pyplot()

    t = (N_ESTIMATION + np.arange(len(y_test))) / FS_HZ
    fig, axes = plt.subplots(2, 1, figsize=(9, 6))
    axes[0].plot(t, y_test, lw=0.6, label="measured")
    axes[0].plot(t, y_sim, lw=0.6, label="simulated (RPEM model)")
    axes[0].plot(t, y_test - y_sim, lw=0.4, label="error")
    axes[0].set_ylabel("output [V]")
    axes[0].legend(fontsize=8, loc="upper right")
    axes[0].set_title(title)
    win = slice(0, 1000)
    axes[1].plot(t[win], y_test[win], label="measured")
    axes[1].plot(t[win], y_sim[win], label="simulated")
    axes[1].plot(t[win], (y_test - y_sim)[win], lw=0.8, label="error")
    axes[1].set_xlabel("time [s]")
    axes[1].set_ylabel("output [V] (first 1000 test samples)")
    fig.tight_layout()
    write_figure(fig, path, dpi=120)


def main(argv: Sequence[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--passes", type=int, default=15, help="largest number of RPEM passes")
    ap.add_argument("--json", type=str, default=None, help="write the figures to this JSON file")
    args = ap.parse_args(argv)
    out = run_folder("wh_benchmark", json_path=args.json)
    u, y = load_benchmark()
    ue, ye, ut, yt = u[:N_ESTIMATION], y[:N_ESTIMATION], u[N_ESTIMATION:], y[N_ESTIMATION:]

    per_method: dict[str, dict] = {}
    models: dict[str, RecursivePEM] = {}
    for method in ("midpoint", "euler"):
        t0 = time.perf_counter()
        est = estimator(method, args.passes).fit(ue, ye)
        sim_e = est.predict(ue, y0=ye[:1])
        sim_t = est.predict(ut, y0=yt[:1])
        per_method[method] = {
            "theta_kalman_init": est.theta_init_,
            "theta": est.theta_,
            "pass_fits_percent": est.pass_fits_,
            "rms_error_mv_estimation": 1000.0 * rms(ye, sim_e),
            "rms_error_mv_test": 1000.0 * rms(yt, sim_t),
            "fit_test": fit_percent(yt, sim_t),
            "seconds": time.perf_counter() - t0,
        }
        models[method] = est
        est.save(out / f"model_{method}")
        r = per_method[method]
        print(f"{method:8s}: RMS error estimation {r['rms_error_mv_estimation']:.1f} mV, test "
              f"{r['rms_error_mv_test']:.1f} mV, test FIT {r['fit_test']:.2f} % ({len(est.pass_fits_)} passes, "
              f"{r['seconds']:.1f} s)")

    selected = min(per_method, key=lambda m: per_method[m]["rms_error_mv_estimation"])
    best = per_method[selected]
    sim_t = models[selected].predict(ut, y0=yt[:1])
    plot(yt, sim_t[:, 0], out / "measured_vs_simulated.png",
         f"Wiener-Hammerstein benchmark, test data: 2nd-order RPEM ({selected}), RMS error "
         f"{best['rms_error_mv_test']:.1f} mV")
    result = {
        "split": "estimation samples 1..100000, test samples 100001..188000 (1-based; benchmark standard)",
        "selected_method": selected,
        "selection_rule": "lower RMS simulation error on the estimation data",
        "rms_error_mv_estimation": best["rms_error_mv_estimation"],
        "rms_error_mv_test": best["rms_error_mv_test"],
        "fit_test": best["fit_test"],
        "rms_error_mv_test_midpoint": per_method["midpoint"]["rms_error_mv_test"],
        "rms_error_mv_test_euler": per_method["euler"]["rms_error_mv_test"],
        "paper_rms_error_mv": 97.5,
        "per_method": per_method,
        "run_folder": str(out),
    }
    save_results(out, "result.json", result, args.json)
    print(f"selected {selected} (estimation RMS): test RMS error {best['rms_error_mv_test']:.1f} mV "
          f"(Paper II: 97.5 mV); plot and models in {out}")
    return result


if __name__ == "__main__":
    main()
