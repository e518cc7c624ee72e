"""The anchors of the benchmark's normalised score: the look-up table (score 0) and the reference (score 100) on every
evaluation episode of every task, stored in scr_env/data/benchmark/anchors.json (never re-solved at evaluation).

    python -m experiments.rl_anchors                          # every task (about 30-60 min on 2 shared cores)
    python -m experiments.rl_anchors --tasks WHTC Aged        # some tasks; the others' stored anchors are kept
    python -m experiments.rl_anchors --merge a.json b.json    # merge anchor files made by parallel runs

The reference (``--reference limit``, the default) is the clairvoyant optimum at the Euro VI 10 ppm mean-slip budget
of the episode's own plant (:func:`control.limit.stored_limit`: the dose that minimises the whole cycle's tailpipe NOx
knowing the plant and the cycle; stored, never re-solved here; a plant not stored raises with the command that solves
it). It is the physical limit of the task, a bound no policy can pass on that plant (with the tasks' actuator lag it
stays a bound, not a tight one). ``--reference oracle`` runs the oracle NMPC instead
(:func:`control.factory.oracle_mpc`: the episode's own catalyst, privileged state, the cycle preview; minutes per
episode). The file says which (``reference_kind``). The look-up table runs each episode of the task's protocol
(:mod:`scr_env.tasks`) through :func:`scr_env.benchmark.episode_metrics`, as any policy's evaluation does.
"""
from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path
from typing import Any

from experiments._runs import run_folder, write_json
from scr_env.benchmark import ANCHORS_PATH, episode_metrics
from scr_env.tasks import TASKS, get_task

REFERENCE_KINDS = {
    "limit": "limit: control.limit.stored_limit(cycle, 10.0, env_kwargs=<the episode's catalyst>, seed=<its seed>), "
             "the clairvoyant whole-cycle optimum at 10 ppm mean slip of the episode's plant "
             "(without the actuator lag)",
    "oracle": "oracle_mpc: control.factory.oracle_mpc() (NMPC on the first-principles catalyst of the episode, "
              "privileged state, cycle preview)"}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="+", default=None, help="task names or ids (default: all)")
    p.add_argument("--out", type=Path, default=ANCHORS_PATH, help="anchors file (default: the shipped one)")
    p.add_argument("--merge", type=Path, nargs="+", default=None, help="merge these anchor files into --out")
    p.add_argument("--reference", choices=sorted(REFERENCE_KINDS), default="limit",
                   help="score-100 anchor: the stored clairvoyant limit (default) or the oracle NMPC")
    p.add_argument("--quick", action="store_true", help="the oracle's quick stages (not for the stored anchors)")
    p.add_argument("--max-steps", type=int, default=None, help="cut episodes short (smoke tests only)")
    p.add_argument("--json", type=Path, default=None, help="also write the result here")
    return p.parse_args(argv)




def _read(path: Path) -> dict[str, Any]:
    return json.loads(path.read_text()) if path.is_file() else {"tasks": {}}


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    command = "python -m experiments.rl_anchors " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    run_folder("rl_anchors", json_path=args.json)
    data = _read(args.out)
    if args.merge:
        for path in args.merge:
            data["tasks"].update(_read(path)["tasks"])
        data["command"] = command
        write_json(args.out, data)
        print(f"merged {len(args.merge)} files into {args.out}: {sorted(data['tasks'])}")
        return data
    from control.baselines import LookupTableDosing
    from control.factory import oracle_mpc
    from control.limit import task_limit_metrics

    tasks = [get_task(t) for t in (args.tasks or list(TASKS))]
    for task in tasks:
        print(f"{task.id}: {task.protocol.n_episodes} episodes", flush=True)
        t0 = time.perf_counter()
        lut = episode_metrics(LookupTableDosing(), task, args.max_steps, progress=True)
        ref = (task_limit_metrics(task) if args.reference == "limit"
               else episode_metrics(oracle_mpc(quick=args.quick), task, args.max_steps, progress=True))
        episodes = [{"condition": a["condition"], "seed": a["seed"], "lookup_table": a["kpis"], "reference": b["kpis"],
                     "wall_time_s": {"lookup_table": a["wall_time_s"], "reference": b["wall_time_s"]}}
                    for a, b in zip(lut, ref, strict=True)]
        bad = [e for e in episodes if not e["reference"]["tailpipe_nox_g_per_kwh"]
               < e["lookup_table"]["tailpipe_nox_g_per_kwh"]]
        if bad:
            raise SystemExit(f"{task.id}: the reference does not beat the look-up table on {len(bad)} episodes")
        data["tasks"][task.id] = {
            "task": task.describe(),
            "reference_kind": REFERENCE_KINDS[args.reference] + (" (quick: horizon 10)" if args.quick else ""),
            "partial_episodes": args.max_steps, "command": command, "wall_time_s": round(time.perf_counter() - t0, 1),
            "episodes": episodes}
        data["command"] = command
        write_json(args.out, data)  # after every task: a long run keeps what it finished
    for task in tasks:
        for e in data["tasks"][task.id]["episodes"]:
            lut, ref = e["lookup_table"], e["reference"]
            print(f"{task.name:10s} {json.dumps(e['condition']):18s} seed {e['seed']:3d}  look-up table "
                  f"{lut['tailpipe_nox_g_per_kwh']:.3f} g/kWh ({lut['mean_nh3_slip_ppm']:.1f} ppm)  reference "
                  f"{ref['tailpipe_nox_g_per_kwh']:.3f} g/kWh ({ref['mean_nh3_slip_ppm']:.1f} ppm)")
    if args.json:
        write_json(args.json, data)
    return data


if __name__ == "__main__":
    main()
