"""The RL benchmark leaderboard: every main task (scr_env.tasks) x every shipped method, the normalised score
(scr_env.benchmark: 0 = look-up table, 100 = reference) as interquartile mean over training seeds with a 95 %
bootstrap interval, and the chatter KPI; learning curves as figures.

    python -m experiments.rl_benchmark --json leaderboard.json
    python -m experiments.rl_benchmark --tasks WHTC --policies runs/smoke/policies --json smoke.json

Methods: the policies in control/policies/benchmark/<dataset group>/<method>_s<seed>.json (``--policies``): PPO,
SAC, TD3 (experiments.train_baselines) and BC (experiments.make_datasets), each evaluated on the task's whole
protocol; one score per training seed (the mean over the protocol's episodes), aggregated by IQM and a percentile
bootstrap over seeds. The anchors: ``lookup_table`` is re-run on the protocol (its score 0 shows that the stored
anchors still hold), ``reference`` is read from the stored anchors (scr_env/data/benchmark/anchors.json; not
re-solved). The single shipped policies of control/policies (``ppo``, ``sac``: one seed, trained before the tasks
existed) are scored beside, as ``<name>_single`` with ``n_seeds`` 1 (``--single`` to choose). The run folder gets
leaderboard.md (the README table), learning_curves_<group>.png and report.json.
"""
from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from experiments._runs import run_folder, save_results, write_figure, write_text


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="+", default=None, help="main task names or ids (default: all main tasks)")
    p.add_argument("--policies", type=Path, default=None, help="folder of <group>/<method>_s<seed>.json")
    p.add_argument("--methods", nargs="+", default=None, help="methods to include (default: all found)")
    p.add_argument("--anchors", type=Path, default=None, help="anchors file (default: the stored one)")
    p.add_argument("--single", nargs="*", default=None, help="single shipped policies of control/policies to score "
                   "beside (default: all of them; entries '<name>_single', 1 seed)")
    p.add_argument("--max-steps", type=int, default=None, help="cut episodes short (smoke tests, with anchors alike)")
    p.add_argument("--out", type=Path, default=None, help="run folder")
    p.add_argument("--json", type=Path, default=None)
    return p.parse_args(argv)


def _fmt(entry: dict) -> str:
    lo, hi = entry["ci"]
    return f"{entry['iqm']:.1f} [{lo:.1f}, {hi:.1f}]"


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    out = run_folder("rl_benchmark", json_path=args.json, folder=args.out)
    command = "python -m experiments.rl_benchmark " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    from control.baselines import LookupTableDosing
    from control.plots import learning_curve_figure
    from control.rl.policy import available_policies, load_policy
    from control.rl.suite import policy_files
    from scr_env.benchmark import aggregate, evaluate, load_anchors
    from scr_env.tasks import MAIN_TASKS, get_task

    anchors = load_anchors(args.anchors)
    tasks = [get_task(t) for t in (args.tasks or MAIN_TASKS)]
    not_main = [t.id for t in tasks if t.id not in MAIN_TASKS]
    if not_main:
        raise SystemExit(f"not main tasks: {not_main}; the leaderboard holds {list(MAIN_TASKS)}")
    t0 = time.perf_counter()
    report: dict = {"command": command, "tasks": {}, "anchors_command": anchors.get("command")}
    groups = {}
    for task in tasks:
        methods = policy_files(task.dataset_group, args.policies)
        groups[task.dataset_group] = methods
        lut = evaluate(LookupTableDosing(), task, anchors, max_steps=args.max_steps)
        ref_eps = anchors["tasks"][task.id]["episodes"]
        ref_chatter = float(np.mean([e["reference"]["command_total_variation_g_s_per_h"] for e in ref_eps]))
        scores = {"lookup_table": {**aggregate([lut.raw_score], learned=False), "n_seeds": len(lut.episodes),
                                   "chatter_g_s_per_h": lut.chatter_g_s_per_h, "over_limit": lut.over_limit,
                                   "note": "anchor (score before the slip penalty), re-run"},
                  "reference": {**aggregate([100.0], learned=False), "n_seeds": len(ref_eps),
                                "chatter_g_s_per_h": ref_chatter, "note": "anchor, stored: "
                                + str(anchors["tasks"][task.id].get("reference_kind", ""))}}
        for method, paths in sorted(methods.items()):
            if args.methods and method not in args.methods:
                continue
            results = [evaluate(load_policy(p), task, anchors, max_steps=args.max_steps) for p in paths]
            entry = aggregate([r.score for r in results])
            entry.update(chatter_g_s_per_h=float(np.mean([r.chatter_g_s_per_h for r in results])),
                         raw_iqm=aggregate([r.raw_score for r in results])["iqm"],
                         over_limit_episodes=int(sum(r.over_limit for r in results)),
                         episodes_per_seed=task.protocol.n_episodes, policies=[str(p) for p in paths])
            scores[method] = entry
            print(f"{task.name:10s} {method:6s} {_fmt(entry)}  chatter {entry['chatter_g_s_per_h']:.0f} g/s/h "
                  f"({len(paths)} seeds)", flush=True)
        for name in (available_policies() if args.single is None else args.single):
            r = evaluate(load_policy(name), task, anchors, max_steps=args.max_steps)
            scores[f"{name}_single"] = {**aggregate([r.score]), "chatter_g_s_per_h": r.chatter_g_s_per_h,
                                        "raw_iqm": r.raw_score, "over_limit_episodes": r.over_limit,
                                        "note": f"control/policies/{name}: one seed, trained without the actuator "
                                                f"on the older setup (not a task baseline)"}
        report["tasks"][task.id] = {"scores": scores, "task": task.describe(),
                                    "reference_kind": anchors["tasks"][task.id].get("reference_kind")}
    report["wall_time_s"] = round(time.perf_counter() - t0, 1)
    methods_all = sorted({m for d in report["tasks"].values() for m in d["scores"]} - {"lookup_table", "reference"})
    cols = ["lookup_table", "reference", *methods_all]
    lines = ["| task | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for tid, d in report["tasks"].items():
        cells = [f"{_fmt(d['scores'][c])}<br>{d['scores'][c]['chatter_g_s_per_h']:.0f} g/s/h" if c in d["scores"]
                 else "-" for c in cols]
        lines.append(f"| `{tid}` | " + " | ".join(cells) + " |")
    table = "\n".join(lines) + (f"\n\nScore: IQM over training seeds [95 % bootstrap interval]; below it the chatter "
                                f"KPI (total variation of the commanded dose per hour). Command: `{command}`\n")
    write_text(out / "leaderboard.md", table)
    print(table)
    for group, methods in groups.items():
        curves = {m: [load_policy(p).metadata for p in paths] for m, paths in methods.items()}
        if curves:
            fig = learning_curve_figure(curves, title=f"learning curves ({group})")
            write_figure(fig, out / f"learning_curves_{group}.png", dpi=110)
    save_results(out, "report.json", report, args.json)
    return report


if __name__ == "__main__":
    main()
