"""The stored limit and what reads it: the plant fingerprint, :func:`stored_limit`, the controllers against the
limit and the Pareto figure."""
from __future__ import annotations

import ast
import hashlib
import io
import itertools
import json
import os
import tokenize
import warnings
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from control.limit.common import REFERENCE_BUDGET_PPM, LimitResult, _count, _positive, gap_to_limit, make_env
from scr_env.cycles import ExhaustTrace

#: the stored limit (package data, written by ``python -m experiments.limit --store``)
STORED_LIMIT_RESOURCE = "data/limit.json"
#: version 2: the numeric parts are signatures compared with a tolerance (version 1 hashed floats rounded to 12
#: significant digits, which flipped when a value sat on a rounding tie and a numpy release changed its last bit)
_FINGERPRINT_VERSION = 2
#: relative tolerance of a numeric signature (of the sum of the absolute terms): far above rounding (1e-16), far
#: below any change of a plant that would move a limit
SIGNATURE_RTOL = 1e-9
_SIGNATURE_PROJECTIONS = 6


# ------------------------------------------------------------------------------------------ fingerprint of a plant
#: arrays up to this many numbers are stored whole in a signature; longer ones as sums and projections per column
_SIGNATURE_WHOLE = 64


def _leaves(obj: Any, path: str = "") -> list[tuple[str, Any]]:
    """(path, leaf) of a nested mapping/list in a fixed order; arrays and scalars are leaves."""
    if isinstance(obj, Mapping):
        return [leaf for k in sorted(obj, key=str) for leaf in _leaves(obj[k], f"{path}/{k}")]
    if isinstance(obj, (list, tuple)) and not all(isinstance(x, (int, float, np.integer, np.floating)) for x in obj):
        return [leaf for i, x in enumerate(obj) for leaf in _leaves(x, f"{path}[{i}]")]
    return [(path, obj)]


def _leaf_signature(leaf: Any) -> Any:
    """A leaf as JSON: non-numeric as its repr; numbers whole up to :data:`_SIGNATURE_WHOLE` of them, else per
    column (the last axis of a 2-D array) the sum of absolute values and a few fixed pseudo-random projections."""
    if isinstance(leaf, (str, bool, np.bool_)) or leaf is None:
        return repr(leaf)
    try:
        x = np.asarray(leaf, dtype=float)
    except (TypeError, ValueError):
        return repr(leaf)
    if x.size <= _SIGNATURE_WHOLE:
        return {"shape": list(x.shape), "values": x.ravel().tolist()}
    cols = x.reshape(x.shape[0], -1) if x.ndim >= 2 else x.reshape(-1, 1)
    w = np.random.default_rng(20261127).standard_normal((_SIGNATURE_PROJECTIONS, cols.shape[0]))
    return {"shape": list(x.shape), "abs_sum": np.abs(cols).sum(axis=0).tolist(), "projections": (w @ cols).tolist()}


def _signature(obj: Any) -> dict[str, Any]:
    """A numeric signature of a nested structure (:func:`_leaf_signature` of every leaf, by path). Two signatures
    are the same plant when their paths, shapes and non-numeric leaves agree and their numbers agree within
    :data:`SIGNATURE_RTOL` (:func:`_same`): immune to the last bits a CPU or a numpy release may change, sensitive to
    any real change of a value."""
    return {path: _leaf_signature(leaf) for path, leaf in _leaves(obj)}


def _close(a: Any, b: Any, scale: Any) -> bool:
    """Whether two number lists agree within :data:`SIGNATURE_RTOL` of ``scale`` (elementwise or per column)."""
    try:
        va, vb = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
        sc = np.asarray(scale, dtype=float)
    except (TypeError, ValueError):
        return False
    if va.shape != vb.shape or not (np.all(np.isfinite(va)) and np.all(np.isfinite(vb))):
        return False
    return bool(np.all(np.abs(va - vb) <= SIGNATURE_RTOL * sc + 1e-300))


def _same(a: Any, b: Any) -> bool:
    """Whether two fingerprint parts describe the same thing: equal strings, or numeric signatures
    (:func:`_signature`) that agree within :data:`SIGNATURE_RTOL`."""
    if isinstance(a, str) or isinstance(b, str) or not isinstance(a, Mapping) or not isinstance(b, Mapping):
        return a == b
    if sorted(a) != sorted(b):
        return False
    for k, la in a.items():
        lb = b[k]
        if isinstance(la, str) or isinstance(lb, str) or not isinstance(la, Mapping) or not isinstance(lb, Mapping):
            if la != lb:
                return False
            continue
        if sorted(la) != sorted(lb) or la.get("shape") != lb.get("shape"):
            return False
        if "values" in la:
            if not _close(la["values"], lb["values"], np.maximum(np.abs(la["values"]), np.abs(lb["values"]))):
                return False
        else:
            scale = np.maximum(np.abs(la["abs_sum"]), np.abs(lb["abs_sum"]))
            if not (_close(la["abs_sum"], lb["abs_sum"], scale)
                    and _close(la["projections"], lb["projections"], scale)):
                return False
    return True


def fingerprint_changes(stored: Mapping[str, Any], now: Mapping[str, Any]) -> list[str]:
    """The parts of a plant fingerprint that differ between a stored one and ``now`` (both
    :func:`plant_fingerprint`); a stored fingerprint of another version differs in every part."""
    if not isinstance(stored, Mapping) or stored.get("version") != now.get("version"):
        return sorted(k for k in now if k != "version")
    return sorted(k for k in now if k != "version" and not _same(stored.get(k), now[k]))


def _source_digest(module: Any) -> str:
    """sha256 (16 hex digits) of a module's code without its comments and docstrings: the tokens of the source,
    so a reworded comment leaves it unchanged and any change of the code changes it."""
    import inspect

    src = inspect.getsource(module)
    doc_lines: set[int] = set()
    for node in ast.walk(ast.parse(src)):
        body = getattr(node, "body", None)
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body:
            first = body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) \
                    and isinstance(first.value.value, str):
                doc_lines.update(range(first.lineno, (first.end_lineno or first.lineno) + 1))
    skip = {tokenize.COMMENT, tokenize.NL, tokenize.ENCODING, tokenize.ENDMARKER}
    parts = [tokenize.tok_name[t.type] if t.type in (tokenize.INDENT, tokenize.DEDENT, tokenize.NEWLINE) else t.string
             for t in tokenize.generate_tokens(io.StringIO(src).readline)
             if t.type not in skip and t.start[0] not in doc_lines]
    return hashlib.sha256("\x00".join(parts).encode()).hexdigest()[:16]


def plant_fingerprint(cycle: str | os.PathLike | ExhaustTrace = "whtc",
                      env_kwargs: Mapping[str, Any] | None = None, seed: int = 0) -> dict[str, Any]:
    """What a limit was solved for: ``catalyst`` (the packed parameters of the episode, by name), ``dosing``
    (injector limit, urea decomposition), ``cycle`` (the drive rows and engine power of every step, dt) and
    ``initial_state`` (coverages and temperatures after reset) as numeric signatures compared with a tolerance
    (:func:`fingerprint_changes`), ``chemistry`` (a hash of the code of :mod:`scr_env.physics.cell`, without
    comments and docstrings) and ``version``. Changes of the kernel's integrator, thermal step or KPI code are not
    in it: ``tests/control/test_limit.py`` replays the stored doses through the current environment for those.
    ``seed``: the reset seed of the episode (as :class:`~control.limit.CycleOptimum`'s)."""
    from dataclasses import asdict

    from scr_env.envs.config import O2_FRACTION
    from scr_env.params import PACKED_FIELDS
    from scr_env.physics import cell

    env = make_env(cycle, env_kwargs)
    env.reset(seed=_count("seed", seed, 0))
    n = env.trace.n_steps
    return {
        "catalyst": _signature(dict(zip(PACKED_FIELDS, env.catalyst_params_array.tolist(), strict=True))),
        "dosing": _signature(asdict(env.config.dosing)),
        "cycle": _signature({"drive": env.disturbance_preview(n), "engine_power_kw": env.trace.engine_power_kw,
                             "dt": env.dt, "o2_fraction": O2_FRACTION}),
        "initial_state": _signature({k: env.state[k] for k in ("nh3_coverage", "temperature_k")}),
        "chemistry": _source_digest(cell),
        "version": _FINGERPRINT_VERSION,
    }


# ----------------------------------------------------------------------------------------------- stored results
class StaleLimitWarning(UserWarning):
    """The stored limit was solved for another plant than the current one (re-solve: ``python -m experiments.limit
    --store``)."""


def stored_limit_path() -> Path:
    """Path of the stored limit in the installed package (:data:`STORED_LIMIT_RESOURCE`)."""
    return Path(str(resources.files("control").joinpath(STORED_LIMIT_RESOURCE)))


_STORED_CACHE: dict[tuple[str, int, int, int], dict[str, Any]] = {}
_FINGERPRINT_CACHE: dict[str, dict[str, str]] = {}


def stored_limits(path: str | os.PathLike | None = None) -> dict[str, Any]:
    """The stored limit document (JSON): ``{"command", "cycles": {cycle: {"fingerprint", "budgets": {"10": record
    of :meth:`LimitResult.to_dict`}}}, ...}``. ``FileNotFoundError`` / ``ValueError`` naming the file if it is
    missing or not a limit document."""
    p = Path(path) if path is not None else stored_limit_path()
    try:
        st = p.stat()
    except FileNotFoundError:
        raise FileNotFoundError(f"no stored limit at {p}: run `python -m experiments.limit --store`") from None
    key = (str(p.resolve()), st.st_mtime_ns, st.st_size, st.st_ino)
    if key not in _STORED_CACHE:
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{p}: not a readable limit document ({exc})") from None
        if not isinstance(doc, dict) or not isinstance(doc.get("cycles"), dict):
            raise ValueError(f"{p}: not a limit document (no 'cycles' mapping)")
        _STORED_CACHE[key] = doc
    return json.loads(json.dumps(_STORED_CACHE[key]))


def _budget_key(budget_ppm: float) -> str:
    return format(_positive("budget_ppm", budget_ppm), "g")


def plant_entry_name(cycle: str, env_kwargs: Mapping[str, Any] | None = None, seed: int = 0) -> str:
    """The name of a plant's entry in the limit document: the cycle (``"whtc"``) for the environment's default
    plant, else e.g. ``"whtc@age_h=4"`` or ``"whtc@randomize=0.2,seed=101"`` (arguments in alphabetical order, the
    seed when it is not 0)."""
    parts = [f"{k}={format(v, 'g') if isinstance(v, float) else v}" for k, v in sorted((env_kwargs or {}).items())]
    parts += [f"seed={seed}"] if seed else []
    return str(cycle) + ("@" + ",".join(parts) if parts else "")


def _find_entry(doc: Mapping[str, Any], cycle: Any, env_kwargs: Mapping[str, Any] | None, seed: int,
                where: Any) -> tuple[str, Any]:
    """(name, entry) of the plant asked for: by name, or for other plant arguments by plant fingerprint."""
    if not isinstance(cycle, str):
        raise ValueError(f"cycle must be a cycle name such as 'whtc', got {cycle!r}")  # noqa: TRY004
    name = cycle.strip().lower()
    if env_kwargs or seed:
        want = plant_fingerprint(name, env_kwargs, seed)
        found = [(n, e) for n, e in doc["cycles"].items() if isinstance(e, dict)
                 and not fingerprint_changes(e.get("fingerprint") or {}, want)]
        if not found:
            raise ValueError(f"no stored limit for the plant {plant_entry_name(name, env_kwargs, seed)} (cycle, "
                             f"env_kwargs, seed); stored in {where}: {', '.join(sorted(doc['cycles']))}. Solve it: "
                             f"CycleOptimum({name!r}, env_kwargs={dict(env_kwargs or {})!r}, seed={seed}).solve(10)")
        return found[0]
    if name not in doc["cycles"]:
        raise ValueError(f"cycle {cycle!r} has no stored limit; stored: {', '.join(sorted(doc['cycles']))}")
    return name, doc["cycles"][name]


def stored_limit(cycle: str = "whtc", budget_ppm: float = REFERENCE_BUDGET_PPM, *,
                 env_kwargs: Mapping[str, Any] | None = None, seed: int = 0,
                 path: str | os.PathLike | None = None, check_plant: bool = True) -> LimitResult:
    """The stored clairvoyant optimum of a cycle at a mean-slip budget [ppm] (never re-solved).

    ``cycle``: ``"whtc"`` or ``"whsc"`` (the hot cycles at 0.5 s with the environment's default catalyst, as
    :mod:`experiments.control_benchmark` runs them), or the name of another stored plant
    (:func:`plant_entry_name`); ``budget_ppm``: one of the stored budgets (1, 2, 5, 10, 20 for the two cycles).
    ``env_kwargs``/``seed``: another plant of the cycle (plant arguments of :class:`CycleOptimum`, e.g.
    ``{"age_h": 4.0}``, or ``{"randomize": 0.2}`` with the episode's reset ``seed``), found among the stored
    entries by its :func:`plant_fingerprint`. ``check_plant``: compare the stored fingerprint with the current
    plant's and warn (:class:`StaleLimitWarning`) if they differ. ``ValueError`` naming the cycle, plant, budget or
    file, listing what is stored. ``float(result)`` (or ``.replay_tailpipe_nox_g_per_kwh``) is the environment's
    NOx of the optimal dose, the figure controllers are compared with; ``result["tailpipe_nox_g_per_kwh"]`` the
    NLP's.
    """
    doc = stored_limits(path)
    where = path if path is not None else stored_limit_path()
    seed = _count("seed", seed, 0)
    name, entry = _find_entry(doc, cycle, env_kwargs, seed, where)
    if not isinstance(entry, dict) or not isinstance(entry.get("budgets", {}), dict):
        raise ValueError(f"{where}: the entry of {name} is not a limit entry (a mapping with 'budgets')")  # noqa: TRY004
    key = _budget_key(budget_ppm)
    if key not in entry.get("budgets", {}):
        raise ValueError(f"budget_ppm {budget_ppm!r}: no stored limit for {name} at that budget; stored: "
                         f"{', '.join(sorted(entry.get('budgets', {}), key=float))} ppm")
    if check_plant:
        stored = entry.get("fingerprint", {})
        plant = (str(entry.get("cycle", name)), entry.get("env_kwargs") or {}, int(entry.get("seed", 0)))
        cache_key = json.dumps(plant, sort_keys=True)
        if cache_key not in _FINGERPRINT_CACHE:
            _FINGERPRINT_CACHE[cache_key] = plant_fingerprint(*plant)
        now = _FINGERPRINT_CACHE[cache_key]
        changed = fingerprint_changes(stored, now)
        if changed:
            warnings.warn(f"the stored limit of {name} was solved for another plant (changed: "
                          f"{', '.join(changed)}); re-solve with `python -m experiments.limit --store`",
                          StaleLimitWarning, stacklevel=2)
    try:
        return LimitResult.from_dict(name, entry["budgets"][key])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{where}: the record of {name} at {key} ppm is not a limit record ({type(exc).__name__}: "
                         f"{exc}); re-solve with `python -m experiments.limit --store`") from None


def limit_nox(cycle: str, budget_ppm: float = REFERENCE_BUDGET_PPM, path: str | os.PathLike | None = None
              ) -> float | None:
    """The stored clairvoyant limit's tailpipe NOx [g/kWh] on ``cycle`` at ``budget_ppm``: the replayed optimum of
    :func:`stored_limit` (never re-solved), for the benchmarks' ``gap_to_limit``. None when nothing is stored for
    that cycle and budget (e.g. a 600 s quick segment) or when it was solved for another plant
    (:class:`StaleLimitWarning`, then not raised): a stale limit is never scored against."""
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            rec = stored_limit(cycle, budget_ppm, path=path)
    except (FileNotFoundError, ValueError):
        return None
    if any(issubclass(w.category, StaleLimitWarning) for w in caught):
        return None
    nox = float(rec.replay_tailpipe_nox_g_per_kwh)
    return nox if np.isfinite(nox) else None


def annotate_gap_to_limit(controllers: Mapping[str, Any], cycle: str,
                          budget_ppm: float = REFERENCE_BUDGET_PPM) -> float | None:
    """Write ``gap_to_limit`` (:func:`gap_to_limit` from the ``lookup_table`` row to the stored limit of ``cycle`` at
    ``budget_ppm``, :func:`limit_nox`) into every row of ``controllers`` (name -> KPI dict with
    ``tailpipe_nox_g_per_kwh``); None in every row when the cycle has no stored limit or no look-up-table row.
    Returns the limit's NOx [g/kWh] or None."""
    lim = limit_nox(cycle, budget_ppm)
    lut = (controllers.get("lookup_table") or {}).get("tailpipe_nox_g_per_kwh")
    for row in controllers.values():
        nox = row.get("tailpipe_nox_g_per_kwh")
        ok = lim is not None and isinstance(lut, (int, float)) and isinstance(nox, (int, float)) and lut > lim
        row["gap_to_limit"] = gap_to_limit(float(lut), float(nox), lim) if ok else None
    return lim


def write_limit_document(doc: Mapping[str, Any], path: str | os.PathLike) -> Path:
    """Write a limit document as JSON, atomically (:func:`scr_env.fileio.write_json`)."""
    from scr_env.fileio import write_json

    return write_json(path, doc, indent=1)


def controllers_against_limit(benchmark: Mapping[str, Any], limit: Mapping[str, Any],
                              budget_ppm: float = REFERENCE_BUDGET_PPM) -> dict[str, dict[str, dict[str, Any]]]:
    """Every controller of a ``control_benchmark`` JSON (``cycles[c]["controllers"][name]``) against the limit of
    a limit document (``cycles[c]["budgets"]``): per cycle and controller its tailpipe NOx [g/kWh] and mean slip
    [ppm], ``within_budget`` (slip <= ``budget_ppm``), ``limit_nox`` (the replayed optimum at that budget),
    ``below_limit`` (within the budget and below the limit: impossible, so something is wrong) and
    ``gap_to_limit`` (:func:`gap_to_limit` from the benchmark's look-up table)."""
    key = _budget_key(budget_ppm)
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for cycle, entry in (benchmark.get("cycles") or {}).items():
        rec = ((limit.get("cycles") or {}).get(cycle) or {}).get("budgets", {}).get(key)
        ctrls = entry.get("controllers") or {}
        if rec is None or not ctrls:
            continue
        lim = float(rec.get("replay_tailpipe_nox_g_per_kwh", rec["tailpipe_nox_g_per_kwh"]))
        lut = (ctrls.get("lookup_table") or {}).get("tailpipe_nox_g_per_kwh")
        rows = {}
        for name, kp in ctrls.items():
            nox, slip = (kp or {}).get("tailpipe_nox_g_per_kwh"), (kp or {}).get("mean_nh3_slip_ppm")
            if not isinstance(nox, (int, float)) or not isinstance(slip, (int, float)):
                continue
            within = slip <= budget_ppm
            rows[name] = {"tailpipe_nox_g_per_kwh": float(nox), "mean_nh3_slip_ppm": float(slip),
                          "within_budget": bool(within), "limit_nox": lim,
                          "below_limit": bool(within and nox < lim * (1.0 - 1e-3)),
                          "gap_to_limit": gap_to_limit(lut, nox, lim) if isinstance(lut, (int, float)) else None}
        out[cycle] = rows
    return out


def pareto_figure(limit: Mapping[str, Any], path: str | os.PathLike,
                  benchmark: Mapping[str, Any] | None = None) -> Path:
    """The NOx-against-slip Pareto front of every cycle of a limit document (replayed optima, one panel per cycle,
    the 10 ppm limit marked), with the controllers of a ``control_benchmark`` JSON placed on it; written
    atomically to ``path``."""
    from control.plots import pyplot
    from scr_env.fileio import atomic_path

    plt = pyplot()
    cycles = list((limit.get("cycles") or {}).keys())
    fig, axes = plt.subplots(1, max(len(cycles), 1), figsize=(5.6 * max(len(cycles), 1) + 2.6, 4.8), squeeze=False)
    placed = controllers_against_limit(benchmark, limit) if benchmark else {}
    for ax, cycle in zip(axes[0], cycles, strict=False):
        recs = sorted(limit["cycles"][cycle].get("budgets", {}).values(), key=lambda r: r["budget_ppm"])
        slip = [r.get("replay_mean_nh3_slip_ppm", r["mean_nh3_slip_ppm"]) for r in recs]
        nox = [r.get("replay_tailpipe_nox_g_per_kwh", r["tailpipe_nox_g_per_kwh"]) for r in recs]
        ax.plot(slip, nox, "k-o", lw=1.6, ms=4, label="clairvoyant optimum (limit)", zorder=3)
        ax.fill_between(slip, 0, nox, color="0.88", label="below the limit: unreachable", zorder=1)
        for r, x, y in zip(recs, slip, nox, strict=True):
            ax.annotate(f"{r['budget_ppm']:g} ppm", (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
        markers = itertools.cycle("sD^v<>pP*Xh")
        for name, row in sorted(placed.get(cycle, {}).items()):
            ax.plot(row["mean_nh3_slip_ppm"], row["tailpipe_nox_g_per_kwh"], next(markers), ms=7, label=name,
                    zorder=4)
        ax.axvline(REFERENCE_BUDGET_PPM, color="tab:red", ls=":", lw=1, label="Euro VI mean-slip limit")
        ax.set_xscale("symlog", linthresh=1.0)
        ax.set_xlim(0, max(max(slip) * 1.5, 25.0))
        ax.set_ylim(0, None)
        ax.set_xlabel("mean NH3 slip [ppm]")
        ax.set_ylabel("tailpipe NOx [g/kWh]")
        ax.set_title(f"hot {cycle.upper()}")
        if ax is axes[0][len(cycles) - 1]:  # one legend, beside the last panel (it hides no controller)
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return Path(path)


def task_limit_metrics(task: Any, budget_ppm: float = REFERENCE_BUDGET_PPM,
                       path: str | os.PathLike | None = None) -> list[dict[str, Any]]:
    """The stored clairvoyant limit of every evaluation episode's plant of a benchmark task (:mod:`scr_env.tasks`),
    as :func:`scr_env.benchmark.episode_metrics` rows (``condition``, ``seed``, ``kpis``, ``wall_time_s``): the
    reference (score 100) of the RL benchmark (``python -m experiments.rl_anchors``). The plant of an episode is its
    catalyst: the condition's ``age_h`` (0 h is the fresh catalyst) and, for a randomised catalyst, the reset seed
    that draws it; sensor-noise seeds of one plant share its limit. The chatter KPIs are the total variation of the
    optimal dose [g/s per hour]. A plant not stored raises ValueError (:func:`stored_limit`)."""
    rows = []
    for condition, seed in task.protocol.episodes():
        plant = {**task.evaluation, **condition}
        kwargs = {k: v for k, v in plant.items() if k in ("age_h", "randomize") and float(v) != 0.0}
        rec = stored_limit(task.protocol.cycle, budget_ppm, env_kwargs=kwargs or None,
                           seed=seed if "randomize" in kwargs else 0, path=path)
        dose = np.asarray(rec.dose_g_s, dtype=float)
        chatter = float(np.abs(np.diff(dose)).sum() / (dose.size * rec.dt / 3600.0))  # g/s per hour
        kpis = {"tailpipe_nox_g_per_kwh": float(rec), "mean_nh3_slip_ppm": float(rec.mean_nh3_slip_ppm),
                "peak_nh3_slip_ppm": float(rec.peak_nh3_slip_ppm), "adblue_g": float(rec.adblue_g),
                "command_total_variation_g_s_per_h": chatter, "adblue_total_variation_g_s_per_h": chatter,
                "nox_conversion": float(rec.replay.get("nox_conversion", float("nan")))}
        rows.append({"condition": condition, "seed": seed, "kpis": kpis, "wall_time_s": 0.0})
    return rows
