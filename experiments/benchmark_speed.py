"""Throughput of the environments (and of RPEM), measured in one process against Gymnasium's Pendulum-v1.

``python -m experiments.benchmark_speed [--json PATH] [--num-envs 1024] [--seconds 2] [--rounds 3]`` (``make bench``).

Reported:
* ``env_steps_per_s``: ``gymnasium.make("scr_env/UreaSCR-v0")`` with its default wrappers, constant action,
  resetting at the end of the cycle;
* ``pendulum_steps_per_s``: ``gymnasium.make("Pendulum-v1")`` the same way (the reference for Python overhead);
* ``vector_env_steps_per_s``: env-steps per second of the native vector environment with ``num_envs`` plants;
* ``rpem_samples_per_s`` (and the full degree-2 model) from :func:`ident.speed.measure_rpem_speed` (``--no-rpem``:
  not measured);
* ``{single,vector}_{cold,warm}_first_step_s`` (and ``..._cpu_s``): seconds from a new process to the end of the
  first step, with an empty numba cache (cold) and with the cache it left (warm), from
  :func:`scr_env.startup.first_step_times` (``--no-first-step``: not measured).
* ``hw_pwl_fit_s``: seconds to fit a piecewise-linear Hammerstein-Wiener model on 10^5 samples
  (:func:`ident.hammerstein_wiener.speed.measure_pwl_fit_speed`, goal 10 s; ``--no-hw``: not measured).
How they are timed: :mod:`scr_env.speed` (``--rounds`` interleaved rounds of ``--seconds``, medians).
"""
from __future__ import annotations

import argparse
from typing import Any

from experiments._runs import write_json
from ident.hammerstein_wiener.speed import measure_pwl_fit_speed
from scr_env.fileio import check_output_file
from scr_env.speed import measure
from scr_env.startup import first_step_times


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", help="write the figures to this JSON file")
    ap.add_argument("--num-envs", type=int, default=1024, help="plants in the vector environment (default 1024)")
    ap.add_argument("--seconds", type=float, default=2.0, help="timing window per figure and round [s] (default 2)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved measuring rounds, median reported (default 3)")
    ap.add_argument("--no-rpem", action="store_true", help="skip the RPEM figures")
    ap.add_argument("--no-first-step", action="store_true", help="skip the cold/warm first-step times")
    ap.add_argument("--no-hw", action="store_true", help="skip the Hammerstein-Wiener fit time")
    args = ap.parse_args(argv)
    if args.num_envs < 1 or args.seconds <= 0 or args.rounds < 1:
        ap.error("--num-envs and --rounds must be >= 1 and --seconds > 0")
    if args.json:
        check_output_file(args.json, "--json file")
    r = measure(args.num_envs, args.seconds, rpem=not args.no_rpem, rounds=args.rounds)
    if not args.no_first_step:
        r.update(first_step_times())
    if not args.no_hw:
        r.update(measure_pwl_fit_speed())
    print(f"Pendulum-v1 (gym.make)        {r['pendulum_steps_per_s']:>12,.0f} steps/s")
    print(f"UreaSCR-v0 single (gym.make)  {r['env_steps_per_s']:>12,.0f} steps/s   "
          f"{r['single_vs_pendulum']:.2f}x Pendulum (goal 0.5x)")
    print(f"UreaSCR-v0 vector ({r['num_envs']} envs)  {r['vector_env_steps_per_s']:>12,.0f} env-steps/s   "
          f"{r['vector_vs_pendulum']:.1f}x Pendulum (goal 20x)")
    for key in ("rpem_samples_per_s", "rpem_full_degree2_samples_per_s"):
        if key in r:
            print(f"{key:30s}{r[key]:>12,.0f} samples/s")
    for kind in ("single", "vector") if "single_cold_first_step_s" in r else ():
        print(f"first step {kind:6s} (new process)  cold {r[f'{kind}_cold_first_step_s']:5.2f} s, "
              f"warm {r[f'{kind}_warm_first_step_s']:5.2f} s   (CPU {r[f'{kind}_cold_first_step_cpu_s']:.2f} / "
              f"{r[f'{kind}_warm_first_step_cpu_s']:.2f} s)")
    if "rpem_error" in r:
        print(r["rpem_error"])
    if "hw_pwl_fit_s" in r:
        print(f"Hammerstein-Wiener PWL fit, {r['hw_pwl_n_samples']:,} samples  {r['hw_pwl_fit_s']:>8.1f} s   "
              f"(goal 10 s; CPU {r['hw_pwl_cpu_s']:.1f} s; validation FIT {r['hw_pwl_validation_fit']:.1f} %)")
    if args.json:
        write_json(args.json, r)
    return r


if __name__ == "__main__":
    main()
