"""The limit of the dosing task: the clairvoyant whole-cycle optimum and its NOx-against-slip Pareto front (#19).

    python -m experiments.limit [--cycles whtc whsc] [--budgets 1 2 5 10 20] [--json PATH]
                                [--benchmark PATH] [--hold-steps 1] [--segment START STEPS] [--store | --stored]
                                [--age-h H] [--randomize SPREAD --seed SEED]

For each cycle (the hot WHTC and WHSC at dt = 0.5 s, started as the environment starts an episode, as
``experiments.control_benchmark`` runs them) and each mean-slip budget [ppm], the dosing that minimises the tailpipe
NOx over the whole cycle, knowing the plant and the cycle in advance (:class:`control.limit.CycleOptimum`, IPOPT on
the plant twin's implicit step, warm-started as :func:`control.limit.pareto_front` says). Reported per budget: the
optimal tailpipe NOx [g/kWh] and mean slip [ppm] of the NLP, the same of its dose replayed open loop through the
environment (``replay_*``), the dose trajectory, the solve time (wall and CPU) and IPOPT's status. Writes
``limit.json`` (``cycles[cycle]["budgets"][str(budget)]``) and ``pareto_front.png`` to ``runs/limit/<stamp>/``.

``--benchmark PATH``: a ``control_benchmark`` JSON whose controllers are placed on the Pareto figure and checked
against the limit (none may be below it within the budget; the run says which are). Without it the figure shows
the front alone. ``--segment START STEPS``: only those steps of each cycle (a short problem, for tests).
``--store``: also write the result as the stored limit of the package (``control/data/limit.json``, read by
:func:`control.limit.stored_limit`; the cycles solved replace theirs); only at the default budgets and hold steps.
``--age-h``/``--randomize``/``--seed``: another plant (an aged catalyst, the catalyst an episode draws at
``reset(seed)``), stored as its own entry (``control.limit.plant_entry_name``). ``--stored``: solve nothing; read
the stored limit (warning if the plant changed since) and draw the figure and the controllers of ``--benchmark``
against it.
"""
from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from control.limit import (
    DEFAULT_BUDGETS_PPM,
    STORED_CYCLES,
    CycleOptimum,
    controllers_against_limit,
    cycle_segment,
    pareto_figure,
    pareto_front,
    plant_entry_name,
    plant_fingerprint,
    replay,
    stored_limit,
    stored_limit_path,
    stored_limits,
    write_limit_document,
)
from experiments._runs import run_folder, save_results, write_json


def _git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10, check=False,
                             cwd=Path(__file__).resolve().parent)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def _read_json(path: Path, what: str) -> dict[str, Any]:
    import json

    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise SystemExit(f"{what} {path}: cannot be read as JSON ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("cycles"), dict):
        raise SystemExit(f"{what} {path}: not a control_benchmark JSON (no 'cycles')")
    return doc


def _stored_document(doc: dict[str, Any]) -> dict[str, Any]:
    """The package's limit document with the cycles of ``doc`` replaced (each cycle keeps its own command)."""
    try:
        stored = stored_limits()
    except (FileNotFoundError, ValueError):
        stored = {"cycles": {}}
    cycles = {c: e for c, e in stored["cycles"].items() if c not in doc["cycles"]}
    cycles.update({c: {**e, "command": doc["command"], "git_commit": doc["git_commit"], "created": doc["created"]}
                   for c, e in doc["cycles"].items()})
    return {**{k: v for k, v in doc.items() if k not in ("cycles", "benchmark", "controllers_against_limit")},
            "command": " ; ".join(sorted({e["command"] for e in cycles.values()})), "cycles": dict(sorted(
                cycles.items()))}


def _plant(args: argparse.Namespace) -> dict[str, Any]:
    """The plant arguments of the run (none: the environment's default catalyst)."""
    return {k: v for k, v in (("age_h", args.age_h), ("randomize", args.randomize)) if v is not None}


def solve_cycle(cycle: str, args: argparse.Namespace) -> dict[str, Any]:
    """The Pareto front of one cycle as a JSON record."""
    t0 = time.perf_counter()
    source = cycle if args.segment is None else cycle_segment(cycle, *args.segment)
    problem = CycleOptimum(source, hold_steps=args.hold_steps, env_kwargs=_plant(args), seed=args.seed)
    setup_s = time.perf_counter() - t0
    problem.prepare()
    build_s = time.perf_counter() - t0 - setup_s
    print(f"{problem.name}: {problem.n_steps} steps, {problem.n_doses} doses, setup {setup_s:.0f} s, NLP built "
          f"{'and compiled ' if problem.jit else ''}in {build_s:.0f} s", flush=True)

    def progress(r: Any) -> None:
        print(f"  {r.budget_ppm:5g} ppm: {r.tailpipe_nox_g_per_kwh:.4f} g/kWh at {r.mean_nh3_slip_ppm:.3f} ppm "
              f"(replay {r.replay_tailpipe_nox_g_per_kwh:.4f} g/kWh, {r.replay_mean_nh3_slip_ppm:.3f} ppm, error "
              f"{r.replay_error:.1e}); {r.status}, {r.reduced_iterations}+{r.iterations - r.reduced_iterations} "
              f"iterations, {r.solve_time_s:.0f} s ({r.solve_cpu_s:.0f} s CPU), from the {r.warm_start}",
              flush=True)

    front = pareto_front(problem, args.budgets, progress=progress)
    lut = replay(source, problem.lookup_table_dose(), _plant(args), seed=args.seed)
    return {"name": problem.name, "cycle": cycle, "env_kwargs": _plant(args), "seed": args.seed,
            "n_steps": problem.n_steps, "dt": problem.dt, "hold_steps": problem.hold_steps,
            "engine_work_kwh": problem.engine_work_kwh, "setup_time_s": setup_s, "build_time_s": build_s,
            "compiled": problem.jit, "fingerprint": plant_fingerprint(source, _plant(args), args.seed),
            "lookup_table": {k: v for k, v in lut.items() if isinstance(v, float)},
            "budgets": {format(b, "g"): r.to_dict() for b, r in front.items()},
            "wall_time_s": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", nargs="+", default=list(STORED_CYCLES), help="cycles (default: whtc whsc)")
    ap.add_argument("--budgets", nargs="+", type=float, default=list(DEFAULT_BUDGETS_PPM),
                    help="mean-slip budgets [ppm] (default: 1 2 5 10 20)")
    ap.add_argument("--json", type=Path, default=None, help="also write the JSON result here")
    ap.add_argument("--benchmark", type=Path, default=None,
                    help="a control_benchmark JSON: its controllers are placed on the figure and checked")
    ap.add_argument("--hold-steps", type=int, default=1, help="plant steps per dose (default 1: every 0.5 s)")
    ap.add_argument("--segment", type=int, nargs=2, default=None, metavar=("START", "STEPS"),
                    help="only these steps of each cycle (a short problem)")
    ap.add_argument("--age-h", type=float, default=None, help="catalyst age [h] (default: fresh)")
    ap.add_argument("--randomize", type=float, default=None, help="catalyst spread (with --seed: an episode's)")
    ap.add_argument("--seed", type=int, default=0, help="reset seed of the episode (default 0)")
    ap.add_argument("--store", action="store_true", help="also write the stored limit of the package")
    ap.add_argument("--stored", action="store_true", help="solve nothing: the stored limit, figure and --benchmark")
    args = ap.parse_args(argv)
    if args.stored and (args.store or args.segment is not None):
        ap.error("--stored reads the package's limit: not with --store or --segment")
    default_plant = not _plant(args) and args.seed == 0
    if args.store and (args.segment is not None or args.hold_steps != 1 or not set(args.cycles) <= set(
            STORED_CYCLES) or (default_plant and sorted(args.budgets) != sorted(DEFAULT_BUDGETS_PPM))):
        ap.error("--store writes the package's limit: only with the stored cycles (whtc, whsc), the default hold "
                 "steps and, for the default plant, the default budgets")
    benchmark = _read_json(args.benchmark, "--benchmark") if args.benchmark is not None else None
    out = run_folder("limit", json_path=args.json)
    command = "python -m experiments.limit " + shlex.join(sys.argv[1:] if argv is None else argv)
    doc: dict[str, Any] = {"command": command.strip(), "git_commit": _git_commit(),
                           "created": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "budgets_ppm": args.budgets,
                           "benchmark": None if args.benchmark is None else str(args.benchmark), "cycles": {}}
    t0 = time.perf_counter()
    for cycle in args.cycles:
        name = plant_entry_name(cycle, _plant(args), args.seed)
        if args.stored:  # a clear error if it is not stored, a StaleLimitWarning if the plant changed
            name = stored_limit(cycle, 10.0, env_kwargs=_plant(args), seed=args.seed).cycle
            doc["cycles"][name] = stored_limits()["cycles"][name]
            for key, r in sorted(doc["cycles"][name]["budgets"].items(), key=lambda kv: float(kv[0])):
                print(f"{name} {key:>3s} ppm: {r['replay_tailpipe_nox_g_per_kwh']:.4f} g/kWh at "
                      f"{r['replay_mean_nh3_slip_ppm']:.3f} ppm (stored, solved in {r['solve_time_s']:.0f} s)")
        else:
            doc["cycles"][name] = solve_cycle(cycle, args)
    doc["wall_time_s"] = time.perf_counter() - t0
    if benchmark is not None:
        placed = controllers_against_limit(benchmark, doc)
        doc["controllers_against_limit"] = placed
        for cycle, rows in placed.items():
            print(f"{cycle}: limit at 10 ppm {next(iter(rows.values()))['limit_nox']:.4f} g/kWh")
            for name, row in rows.items():
                flag = "BELOW THE LIMIT" if row["below_limit"] else ("" if row["within_budget"] else "over 10 ppm")
                gap = row["gap_to_limit"]
                print(f"  {name:28s} {row['tailpipe_nox_g_per_kwh']:.3f} g/kWh at {row['mean_nh3_slip_ppm']:5.2f} "
                      f"ppm, gap to limit closed {gap if gap is None else f'{gap:.2f}'} {flag}")
    pareto_figure(doc, out / "pareto_front.png", benchmark)
    save_results(out, "limit.json", doc, args.json)
    if args.store:  # the cycles solved replace theirs in the stored document; the others are kept
        stored = _stored_document(doc)
        path = write_limit_document(stored, stored_limit_path())
        print(f"stored the limit of {', '.join(doc['cycles'])} in {path}")
    write_json(out / "command.json", {"command": doc["command"]})
    print(f"wrote {out} in {doc['wall_time_s']:.0f} s")
    return doc


if __name__ == "__main__":
    main()
