"""Time to the first step of the environments, cold and warm, and compiling ahead of time.

The plant step is machine code compiled by numba at its first call and cached on disk (:mod:`scr_env.jit`). So the
first step of a new process takes seconds when nothing is cached yet (*cold*: a new install, an upgrade, an edited
source file) and well under a second afterwards (*warm*: loaded from the cache). :func:`first_step_times` measures
both in fresh processes (``make bench`` prints them); :func:`precompile` pays the cold cost once, ahead of time
(``python -m scr_env.startup --precompile``, e.g. when building a container image or after ``pip install``).

What is compiled: the per-plant step (chemistry, heat balance, dosing, sensors, reward and KPIs, about 3 s of CPU
on the development machine) serves both environments; the vector environment adds its action, noise and
bookkeeping functions (about 1 s), and for batches of 64 plants or more with more than one numba thread, a threaded
variant of its step, compiled at the third step (about 1 s more).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from typing import Any

__all__ = ["first_step_times", "precompile"]

# The measured child: from interpreter start to the end of the first step, wall and CPU time.
_CHILD = r'''
import time
t0 = time.perf_counter()
import json, sys
import numpy as np
import gymnasium as gym
import scr_env
t1 = time.perf_counter()
kind, n = sys.argv[1], int(sys.argv[2])
if kind == "single":
    env = gym.make("scr_env/UreaSCR-v0")
    env.reset(seed=0)
    env.step(np.zeros(1, dtype=np.float32))
else:
    env = gym.make_vec("scr_env/UreaSCR-v0", num_envs=n, vectorization_mode="vector_entry_point")
    env.reset(seed=0)
    env.step(np.zeros((n, 1), dtype=np.float32))
t2 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "first_step_s": t2 - t0, "first_step_cpu_s": time.process_time()}))
'''


def _run_child(kind: str, num_envs: int, cache_dir: str) -> dict[str, float]:
    env = {**os.environ, "NUMBA_CACHE_DIR": cache_dir}
    proc = subprocess.run([sys.executable, "-c", _CHILD, kind, str(num_envs)], capture_output=True, text=True,
                          env=env, timeout=600, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"first-step measurement ({kind}) failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def first_step_times(num_envs: int = 64, repeats: int = 1) -> dict[str, Any]:
    """Seconds from a new Python process to the end of the first ``step``, cold and warm, for the single
    environment (``gym.make``) and the vector environment (``gym.make_vec``, ``num_envs`` plants).

    Cold: an empty numba cache (a fresh temporary ``NUMBA_CACHE_DIR``, so the user's cache is neither used nor
    changed); warm: a second process on that cache. Each figure is the median of ``repeats`` measurements and
    includes the imports (``import_s``); ``*_cpu_s`` is the CPU time of the process, which a busy machine inflates
    less than the wall time.
    """
    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
        raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise ValueError(f"repeats must be a positive integer, got {repeats!r}")
    import numpy as np

    samples: dict[str, list[float]] = {}
    for _ in range(repeats):
        for kind in ("single", "vector"):
            with tempfile.TemporaryDirectory(prefix="scr-dosing-cold-") as cache:
                for state in ("cold", "warm"):
                    r = _run_child(kind, num_envs, cache)
                    samples.setdefault(f"{kind}_{state}_first_step_s", []).append(r["first_step_s"])
                    samples.setdefault(f"{kind}_{state}_first_step_cpu_s", []).append(r["first_step_cpu_s"])
                    samples.setdefault(f"{kind}_{state}_import_s", []).append(r["import_s"])
    out: dict[str, Any] = {key: float(np.median(v)) for key, v in samples.items()}
    out["first_step_num_envs"] = num_envs
    out["first_step_samples"] = samples
    return out


def precompile(vector: bool = True) -> None:
    """Compile the steps of the single environment and (``vector``) of the vector environment now, serial and
    threaded, into numba's cache (:func:`scr_env.jit.cache_directory`), so that later processes start warm."""
    import gymnasium as gym
    import numpy as np

    import scr_env  # noqa: F401  (registers the environments)

    env = gym.make("scr_env/UreaSCR-v0")
    env.reset(seed=0)
    env.step(np.zeros(1, dtype=np.float32))
    env.close()
    if vector:
        n = 64
        venv = gym.make_vec("scr_env/UreaSCR-v0", num_envs=n, vectorization_mode="vector_entry_point")
        venv.reset(seed=0)
        for _ in range(4):  # the serial variant, then the threaded one (with more than one numba thread)
            venv.step(np.zeros((n, 1), dtype=np.float32))
        venv.close()


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--precompile", action="store_true", help="compile and cache the environments' steps now")
    ap.add_argument("--num-envs", type=int, default=64, help="plants of the measured vector environment")
    ap.add_argument("--repeats", type=int, default=1, help="measurements per figure (median)")
    args = ap.parse_args()
    if args.precompile:
        from scr_env.jit import cache_directory

        precompile()
        print(f"compiled into {cache_directory()}")
    else:
        r = first_step_times(args.num_envs, args.repeats)
        for kind in ("single", "vector"):
            print(f"{kind:6s} first step: cold {r[f'{kind}_cold_first_step_s']:.2f} s "
                  f"({r[f'{kind}_cold_first_step_cpu_s']:.2f} s CPU), warm {r[f'{kind}_warm_first_step_s']:.2f} s "
                  f"({r[f'{kind}_warm_first_step_cpu_s']:.2f} s CPU)")
