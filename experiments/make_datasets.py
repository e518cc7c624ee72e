"""Offline datasets of the main benchmark tasks in Minari format (expert, medium, random, mixed per dataset group),
and the behaviour-cloning baseline trained on each group's expert dataset.

    MINARI_DATASETS_PATH=runs/datasets python -m experiments.make_datasets --seed 0
    MINARI_DATASETS_PATH=runs/datasets python -m experiments.make_datasets --groups fresh --episodes 2 --duration-s 300
    python -m experiments.make_datasets --root runs/datasets --bc-seeds 0 1 2 3 4 --ship-bc

Defaults: every group (fresh = WHTC/WHSC, aged, randomised), 4 episodes of 900 s per behaviour kind, reset seeds
``--seed`` .. ``--seed + 3`` on each group's training distribution (control.rl.datasets documents what is recorded and
what is omitted). The expert (oracle NMPC) sets the wall time: about 5 min per group on 2 cores shared with other
jobs. Then ``--bc-seeds`` BC policies (control.rl.bc, seconds each) per group, written to the run folder, and with
``--ship-bc`` to control/policies/benchmark/<group>/bc_s<seed>.json, where experiments.rl_benchmark finds them.
"""
from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

from experiments._runs import run_folder, save_results

BENCHMARK_POLICIES = Path(__file__).resolve().parent.parent / "control" / "policies" / "benchmark"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--groups", nargs="+", default=None, help="dataset groups (default: fresh aged randomised)")
    p.add_argument("--kinds", nargs="+", default=None, help="dataset kinds (default: expert medium random mixed)")
    p.add_argument("--episodes", type=int, default=4, help="episodes per dataset")
    p.add_argument("--duration-s", type=float, default=900.0, help="length of each random cycle [s]")
    p.add_argument("--seed", type=int, default=0, help="reset seed of the first episode")
    p.add_argument("--root", type=Path, default=None, help="datasets folder (default: $MINARI_DATASETS_PATH or "
                                                            "Minari's ~/.minari/datasets)")
    p.add_argument("--quick", action="store_true", help="the oracle's quick stages: half of each kind (smoke tests)")
    p.add_argument("--max-steps", type=int, default=None, help="cut episodes short (smoke tests)")
    p.add_argument("--bc-seeds", type=int, nargs="*", default=[0, 1, 2, 3, 4], help="BC training seeds")
    p.add_argument("--ship-bc", action="store_true", help="write the BC policies to --policies")
    p.add_argument("--policies", type=Path, default=BENCHMARK_POLICIES, help="policy folder of --ship-bc")
    p.add_argument("--out", type=Path, default=None, help="run folder")
    p.add_argument("--json", type=Path, default=None)
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    out = run_folder("make_datasets", json_path=args.json, folder=args.out)
    command = "python -m experiments.make_datasets " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    from control.rl.bc import train_bc
    from control.rl.datasets import DATASET_GROUPS, KINDS, datasets_root, make_group
    from control.rl.policy import save_policy

    groups = args.groups or list(DATASET_GROUPS)
    kinds = tuple(args.kinds or KINDS)
    report: dict = {"command": command, "seed": args.seed, "episodes": args.episodes, "duration_s": args.duration_s,
                    "groups": {}}
    with datasets_root(args.root):
        for group in groups:
            t0 = time.perf_counter()
            made = make_group(group, args.episodes, args.seed, args.duration_s, args.quick, args.max_steps, kinds)
            entry = {"wall_time_s": round(time.perf_counter() - t0, 1), "datasets": {}}
            for kind, ds in made.items():
                returns = [float(ep.rewards.sum()) for ep in ds.iterate_episodes()]
                entry["datasets"][kind] = {"id": ds.spec.dataset_id, "episodes": ds.total_episodes,
                                           "steps": ds.total_steps, "mean_return": sum(returns) / len(returns),
                                           "path": str(ds.spec.data_path)}
                print(f"{ds.spec.dataset_id:34s} {ds.total_episodes:3d} episodes {ds.total_steps:7d} steps, mean "
                      f"return {sum(returns) / len(returns):9.1f}", flush=True)
            entry["bc"] = {}
            if "expert" in made:
                for seed in args.bc_seeds:
                    policy, meta = train_bc(made["expert"], seed=seed)
                    meta.update(command=command, group=group, trained_on=made["expert"].spec.dataset_id)
                    folders = [out / "bc" / group] + ([args.policies / group] if args.ship_bc else [])
                    for folder in folders:
                        path = save_policy(policy.model, policy.obs_mean, policy.obs_var, folder, f"bc_s{seed}", meta)
                    entry["bc"][seed] = {"policy": str(path), "wall_time_s": meta["wall_time_s"],
                                         "final_mse": meta["learning_curve"]["mse"][-1]}
                    print(f"  bc seed {seed}: {meta['samples']} samples, {meta['wall_time_s']:.1f} s, final MSE "
                          f"{meta['learning_curve']['mse'][-1]:.4f}", flush=True)
            report["groups"][group] = entry
    save_results(out, "report.json", report, args.json)
    return report


if __name__ == "__main__":
    main()
