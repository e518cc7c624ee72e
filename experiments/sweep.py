"""Run the tasks of an experiment sweep (seeds x cycles x controllers) in parallel: local processes by default,
a Ray cluster when given its address, so a study that outgrows one machine runs unchanged on many.

>>> from experiments.sweep import run_sweep
>>> results = run_sweep(my_function, [{"seed": s, "cycle": c} for s in range(4) for c in ("whtc", "whsc")])

``my_function(**task)`` must be importable (a module-level function) and return something picklable. Results
come back in the order of the tasks. Backends:

* ``"serial"``: in this process (debugging, or one worker);
* ``"local"`` (default): a :class:`concurrent.futures.ProcessPoolExecutor` with ``workers`` processes
  (default: the number of CPUs);
* ``"ray"``: Ray tasks on the cluster at ``address`` (``"auto"``, ``"ray://host:10001"``, or ``None`` for a local
  Ray instance started on the spot). Ray is an optional extra: ``pip install "scr-dosing[ray]"``.

Command-line scripts take ``--workers N`` and ``--ray-address ADDR`` and pass them through :func:`add_arguments`
and :func:`from_args`.
"""
from __future__ import annotations

import argparse
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

BACKENDS = ("serial", "local", "ray")


def _call(fn: Callable[..., Any], task: dict[str, Any]) -> Any:
    return fn(**task)


def run_sweep(fn: Callable[..., Any], tasks: Sequence[dict[str, Any]], backend: str = "local",
              workers: int | None = None, address: str | None = None, progress: bool = True,
              description: str = "sweep") -> list[Any]:
    """Evaluate ``fn(**task)`` for every task; results in task order.

    Parameters
    ----------
    fn : module-level function (picklable by reference).
    tasks : keyword-argument dicts, one per task.
    backend : "serial", "local" (processes) or "ray".
    workers : processes for "local" (default ``os.cpu_count()``); ignored otherwise.
    address : Ray cluster address for "ray" (None starts a local Ray instance).
    progress : show a tqdm progress bar.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if not callable(fn):
        raise ValueError("fn must be callable")  # noqa: TRY004  (ValueError naming the argument, as every check)
    tasks = list(tasks)
    for i, t in enumerate(tasks):
        if not isinstance(t, dict):
            raise ValueError(  # noqa: TRY004  (ValueError naming the argument, as every check)
                f"tasks[{i}] must be a dict of keyword arguments, got {type(t).__name__}")
    if not tasks:
        return []
    if workers is not None and (not isinstance(workers, int) or workers < 1):
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    from tqdm.auto import tqdm

    bar = tqdm(total=len(tasks), desc=description, disable=not progress)
    try:
        if backend == "serial" or (backend == "local" and (workers == 1 or len(tasks) == 1)):
            results = []
            for t in tasks:
                results.append(fn(**t))
                bar.update()
            return results
        if backend == "local":
            n = min(workers or os.cpu_count() or 1, len(tasks))
            with ProcessPoolExecutor(max_workers=n) as pool:
                futures = [pool.submit(_call, fn, t) for t in tasks]
                results = []
                for f in futures:
                    results.append(f.result())
                    bar.update()
            return results
        return _run_ray(fn, tasks, address, bar)
    finally:
        bar.close()


def _run_ray(fn: Callable[..., Any], tasks: list[dict[str, Any]], address: str | None, bar: Any) -> list[Any]:
    try:
        import ray
    except ImportError as e:  # pragma: no cover - depends on the optional extra
        raise ImportError('the "ray" backend needs Ray: pip install "scr-dosing[ray]"') from e
    started_here = False
    if not ray.is_initialized():
        # A local instance when no address is given. Workers import the project from the installed package, so
        # every node of a cluster needs the project installed (pip install scr-dosing) in the same environment.
        ray.init(address=address, include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)
        started_here = address is None
    try:
        remote = ray.remote(_call)
        refs = [remote.remote(fn, t) for t in tasks]
        index = {r: i for i, r in enumerate(refs)}
        results: list[Any] = [None] * len(refs)
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for r in done:
                results[index[r]] = ray.get(r)
                bar.update()
        return results
    finally:
        if started_here:
            ray.shutdown()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--workers`` and ``--ray-address`` to an experiment's command line."""
    parser.add_argument("--workers", type=int, default=None,
                        help="local worker processes for the sweep (default: number of CPUs; 1 = serial)")
    parser.add_argument("--ray-address", default=None,
                        help="run the sweep on this Ray cluster ('auto' or 'ray://host:port') instead of locally")


def from_args(args: argparse.Namespace) -> dict[str, Any]:
    """Keyword arguments of :func:`run_sweep` from the parsed ``--workers`` / ``--ray-address``."""
    if getattr(args, "ray_address", None):
        return {"backend": "ray", "address": args.ray_address}
    return {"backend": "local", "workers": getattr(args, "workers", None)}
