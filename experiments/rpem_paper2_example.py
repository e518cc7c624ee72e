"""Paper II, section 4: RPEM on the simulated system dx1/dt = x2, dx2/dt = 2u - x1 - x2 - x1 u, y = x1 + e.

Two protocols, each over 10 seeds of input and noise (ALGORITHMS.md section 4):

1. The paper's: data from the *scaled midpoint model itself* (sampling period T = 0.1 s, alpha = 1.5, so the
   data-generating step is the midpoint rule on Ts = 0.15) and the estimate, with the same alpha, is compared with
   the true theta directly (with data from the scaled model, alpha does not change the meaning of theta).
2. The same system integrated finely in continuous time (RK4, 20 sub-steps, zero-order-hold input), sampled at
   T = 0.1 s and identified with alpha = 1 (so that theta is comparable to the continuous-time parameters), once
   with midpoint and once with Euler discretisation: the fair comparison of the two.

Both use the paper's tuning: theta(0) = (0, 0.5, -0.5, 0, -0.25, 0, 0, 0), R(0) = 100 I, Lambda(0) = 0.1,
delta = 0.015, the held input at the midpoint half step, and a forgetting factor rising from 0.999 to 1 at rate
0.999. One pass over 10000 samples, as in the paper.

Usage: ``python -m experiments.rpem_paper2_example [--seeds 10] [--json PATH]``
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence

import numpy as np

from control.plots import pyplot
from experiments._runs import run_folder, save_results, write_figure
from ident.rpem import PAPER2_TERMS, RecursivePEM
from scr_env.jit import njit

THETA_TRUE = np.array([0.0, 2.0, -1.0, 0.0, -1.0, -1.0, 0.0, 0.0])
THETA_START = np.array([0.0, 0.5, -0.5, 0.0, -0.25, 0.0, 0.0, 0.0])
T_SAMPLE_S = 0.1
N_SAMPLES = 10_000
NOISE_STD = 0.1


def prbs_levels(rng: np.random.Generator, n: int, low: float = -0.5, high: float = 1.5,
                min_hold: int = 5, max_hold: int = 40) -> np.ndarray:
    """PRBS-like input with varying amplitude: random levels in [low, high] held for a random number of samples.

    The levels stay above -1, where the true system (stiffness 1 + u) is stable.
    """
    u = np.empty(n)
    t = 0
    while t < n:
        hold = int(rng.integers(min_hold, max_hold + 1))
        u[t:t + hold] = rng.uniform(low, high)
        t += hold
    return u


@njit(cache=True)
def _rhs(x1: float, x2: float, u: float) -> tuple[float, float]:
    return x2, 2.0 * u - x1 - x2 - x1 * u


@njit(cache=True)
def simulate_scaled_midpoint(u: np.ndarray, ts: float) -> np.ndarray:
    """Noise-free output of the scaled midpoint model (the paper's data generator)."""
    y = np.empty(u.shape[0])
    x1, x2 = 0.0, 0.0
    for t in range(u.shape[0]):
        y[t] = x1
        f1, f2 = _rhs(x1, x2, u[t])
        g1, g2 = _rhs(x1 + 0.5 * ts * f1, x2 + 0.5 * ts * f2, u[t])
        x1, x2 = x1 + ts * g1, x2 + ts * g2
    return y


@njit(cache=True)
def simulate_continuous(u: np.ndarray, t_sample: float, substeps: int) -> np.ndarray:
    """Noise-free output of the continuous-time system (RK4, zero-order-hold input) sampled every t_sample."""
    y = np.empty(u.shape[0])
    x1, x2 = 0.0, 0.0
    h = t_sample / substeps
    for t in range(u.shape[0]):
        y[t] = x1
        for _ in range(substeps):
            a1, a2 = _rhs(x1, x2, u[t])
            b1, b2 = _rhs(x1 + 0.5 * h * a1, x2 + 0.5 * h * a2, u[t])
            c1, c2 = _rhs(x1 + 0.5 * h * b1, x2 + 0.5 * h * b2, u[t])
            d1, d2 = _rhs(x1 + h * c1, x2 + h * c2, u[t])
            x1 += h / 6.0 * (a1 + 2 * b1 + 2 * c1 + d1)
            x2 += h / 6.0 * (a2 + 2 * b2 + 2 * c2 + d2)
    return y


def make_data(seed: int, continuous: bool) -> tuple[np.ndarray, np.ndarray]:
    """Input and noisy output of one seed."""
    rng = np.random.default_rng(seed)
    u = prbs_levels(rng, N_SAMPLES)
    y = simulate_continuous(u, T_SAMPLE_S, 20) if continuous else simulate_scaled_midpoint(u, 1.5 * T_SAMPLE_S)
    return u, y + NOISE_STD * rng.standard_normal(N_SAMPLES)


def estimator(alpha: float, method: str = "midpoint") -> RecursivePEM:
    """The paper's RPEM set-up."""
    return RecursivePEM(n_states=2, terms=PAPER2_TERMS, sampling_period=T_SAMPLE_S, alpha=alpha, method=method,
                        half_step_input="hold", stability_margin=0.015, theta0=THETA_START, R0=100.0,
                        Lambda0=0.1, forgetting_initial=0.999, forgetting_rate=0.999)


def run_recursively(est: RecursivePEM, u: np.ndarray, y: np.ndarray, chunk: int = 50) -> np.ndarray:
    """Feed the data in chunks through ``partial_fit`` (identical to one pass of ``fit``); theta every chunk."""
    history = [np.asarray(est.theta0, dtype=float)]
    for start in range(0, len(u), chunk):
        est.partial_fit(u[start:start + chunk], y[start:start + chunk])
        history.append(est.theta_.copy())
    return np.array(history)


def plot_convergence(history: np.ndarray, chunk: int, path) -> None:
    plt = pyplot()

    t = np.arange(len(history)) * chunk * T_SAMPLE_S
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for j in range(history.shape[1]):
        line, = ax.plot(t, history[:, j], lw=1.2, label=f"theta{j + 1} ({PAPER2_TERMS[j]})")
        ax.axhline(THETA_TRUE[j], color=line.get_color(), ls="--", lw=0.8)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("parameter estimate")
    ax.set_title("RPEM parameter convergence, Paper II example (seed 0; dashed: true values)")
    ax.legend(fontsize=7, ncol=2, loc="lower right")
    fig.tight_layout()
    write_figure(fig, path, dpi=120)


def main(argv: Sequence[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10, help="number of seeds (0 .. seeds-1)")
    ap.add_argument("--json", type=str, default=None, help="write the figures to this JSON file")
    args = ap.parse_args(argv)
    out = run_folder("rpem_paper2_example", json_path=args.json)
    chunk = 50

    errors, theta_final, rejected = [], None, []
    for seed in range(args.seeds):
        u, y = make_data(seed, continuous=False)
        est = estimator(alpha=1.5)
        history = run_recursively(est, u, y, chunk)
        errors.append(float(np.max(np.abs(est.theta_ - THETA_TRUE))))
        rejected.append(est.n_rejected_)
        if seed == 0:
            theta_final = est.theta_.copy()
            plot_convergence(history, chunk, out / "parameter_convergence.png")
        print(f"seed {seed}: theta = {np.round(est.theta_, 4)}, max|error| = {errors[-1]:.4f}")

    cont: dict[str, list[float]] = {"midpoint": [], "euler": []}
    for seed in range(args.seeds):
        u, y = make_data(seed, continuous=True)
        for method, errs in cont.items():
            est = estimator(alpha=1.0, method=method).fit(u, y)
            errs.append(float(np.max(np.abs(est.theta_ - THETA_TRUE))))

    result = {
        "protocol": "scaled midpoint data, T = 0.1 s, alpha = 1.5 in data and estimator, 10000 samples, one pass; "
                    "continuous-time data (RK4, ZOH input) with alpha = 1",
        "theta_true": THETA_TRUE,
        "theta_final": theta_final,
        "theta_paper": [-0.0009, 2.0684, -1.0001, 0.0472, -1.0214, -1.0195, -0.0286, 0.0132],
        "max_abs_error_per_seed": errors,
        "max_abs_error": float(np.median(errors)),
        "rejected_updates_per_seed": rejected,
        "continuous_midpoint_errors": cont["midpoint"],
        "continuous_euler_errors": cont["euler"],
        "continuous_midpoint_median_error": float(np.median(cont["midpoint"])),
        "continuous_euler_median_error": float(np.median(cont["euler"])),
        "run_folder": str(out),
    }
    save_results(out, "result.json", result, args.json)
    print(f"median max|theta - theta_true| over {args.seeds} seeds: {result['max_abs_error']:.4f} "
          f"(worst {max(errors):.4f})")
    print(f"continuous-time data, alpha = 1: midpoint {result['continuous_midpoint_median_error']:.4f}, "
          f"Euler {result['continuous_euler_median_error']:.4f}")
    print(f"plot and result written to {out}")
    return result


if __name__ == "__main__":
    main()
