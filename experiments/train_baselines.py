"""Train the benchmark's RL baselines: PPO, SAC and TD3 x 5 seeds x each dataset group, unattended, at most 2 processes.

    NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 python -m experiments.train_baselines --jobs 2 --ship
    python -m experiments.train_baselines --groups fresh --algos sac --seeds 0 --timesteps 2000 --out runs/smoke
    python -m experiments.train_baselines --speed 3000          # steps per second of each algorithm, then stop

Each run (control.rl.suite.train_one) trains on its group's training distribution (scr_env.tasks), validates its
checkpoints on random cycles of that distribution and keeps the selected one (flagged if over the slip limit); with
``--ship`` it goes to control/policies/benchmark/<group>/<algo>_s<seed>.json, where experiments.rl_benchmark finds
it. Default timesteps: control.rl.suite.SUITE_TIMESTEPS (PPO 500 k, SAC 200 k, TD3 200 k): the 45 runs take
about 85 min of one core (--jobs 1, under load; SAC at 100 k took 21 min for its 15 runs, TD3 27, PPO 16);
``--timesteps`` overrides every run's. The report (``--json``, and report.json in the run folder) gives every
run's wall time, steps per second and selection.
Retrain after the plant changes (the phys stream's chemistry and ageing) or the reference does (control.limit).
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from experiments._runs import run_folder, save_results


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--groups", nargs="+", default=["fresh", "aged", "randomised"])
    p.add_argument("--algos", nargs="+", default=["ppo", "sac", "td3"], choices=("ppo", "sac", "td3"))
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    p.add_argument("--timesteps", type=int, default=None, help="per run (default: SUITE_TIMESTEPS per algorithm)")
    p.add_argument("--jobs", type=int, default=2, choices=(1, 2), help="parallel processes (at most 2)")
    p.add_argument("--ship", action="store_true", help="install the selected policies in --policies")
    p.add_argument("--policies", type=Path, default=None, help="policy folder (default control/policies/benchmark)")
    p.add_argument("--validation-s", type=float, default=None, help="validation cycle length [s] (smoke tests)")
    p.add_argument("--speed", type=int, default=None, metavar="STEPS", help="only measure steps/s of each algorithm")
    p.add_argument("--out", type=Path, default=None, help="run folder")
    p.add_argument("--json", type=Path, default=None)
    return p.parse_args(argv)


def _one(job: tuple) -> dict:
    from control.rl.suite import train_one

    group, algo, seed, timesteps, out, ship, command, validation_s = job
    t0 = time.perf_counter()
    try:
        summary = train_one(group, algo, seed, timesteps, out, ship, command=command,
                            validation_duration_s=validation_s)
    except Exception as exc:  # noqa: BLE001  (one failed run is reported; the others go on)
        summary = {"group": group, "algo": algo, "seed": seed, "error": f"{type(exc).__name__}: {exc}"}
    summary["job_wall_time_s"] = round(time.perf_counter() - t0, 1)
    print(json.dumps({k: summary.get(k) for k in ("group", "algo", "seed", "wall_time_s", "steps_per_s",
                                                  "within_slip_limit", "error")}), flush=True)
    return summary


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    out = run_folder("train_baselines", json_path=args.json, folder=args.out)
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    command = "python -m experiments.train_baselines " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    t0 = time.perf_counter()
    if args.speed:
        from control.rl.suite import measure_speed

        report = {"command": command, "speed": [measure_speed(a, args.speed) for a in args.algos]}
        for r in report["speed"]:
            print(f"{r['algo']}: {r['timesteps']} steps in {r['wall_time_s']} s = {r['steps_per_s']} steps/s "
                  f"(+{r['setup_s']} s setup)")
    else:
        from control.rl.suite import BENCHMARK_POLICY_DIR

        base = args.policies or BENCHMARK_POLICY_DIR
        jobs = [(g, a, s, args.timesteps, str(out), str(base / g) if args.ship else None, command, args.validation_s)
                for g in args.groups for a in args.algos for s in args.seeds]
        if args.jobs == 1:
            runs = [_one(j) for j in jobs]
        else:
            with ProcessPoolExecutor(max_workers=args.jobs) as pool:
                runs = list(pool.map(_one, jobs))
        report = {"command": command, "runs": runs, "failed": [r for r in runs if "error" in r]}
    report["wall_time_s"] = round(time.perf_counter() - t0, 1)
    save_results(out, "report.json", report, args.json)
    print(f"done in {report['wall_time_s']:.0f} s; report {out / 'report.json'}")
    return report


if __name__ == "__main__":
    main()
