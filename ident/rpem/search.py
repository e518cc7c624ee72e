"""Automatic choice of the RPEM model structure: :class:`StructureSearch`, a small model-selection helper in the
manner of scikit-learn's ``GridSearchCV``, scored on an inner hold-out of the estimation record.

The structure of a :class:`~ident.rpem.RecursivePEM` model is what :data:`~ident.rpem.AUTO_SETTINGS` leaves to the
user: the chain length ``n_states`` (the order of the dynamics), the polynomial right-hand side (all monomials of
states and inputs up to ``total_degree``) and the static output function (identity, ``abs`` for a sensor that
ignores the sign, ``saturation``, ``polynomial``). The search tries a small grid in two stages and keeps the
structure with the best simulation FIT on the hold-out (the last ``holdout`` fraction of the estimation record,
never any validation data):

1. **order and output function**, with linear dynamics (``total_degree`` = the smallest degree of ``degrees``):
   every ``n_states`` of ``orders`` with every output function of ``outputs``;
2. **polynomial degree**: the ``n_finalists`` orders with the best hold-out FIT in stage 1, each with its simplest
   output function among those within ``tolerance`` of that order's best (plus the identity output at the best
   order), with every larger degree of ``degrees`` (structures of more than ``max_terms`` terms per output are
   skipped and listed as such).

Among the structures whose hold-out FIT is within ``tolerance`` FIT points of the best, the one with the fewest
parameters is chosen (the hold-out of a short record is noisy; a simpler model that scores as well generalises at
least as well). Every candidate is fitted with the same automatic settings (:data:`AUTO_SETTINGS`, or
``settings``), so the search adds no choice of its own beyond the grid.

Cost: stages 1 and 2 are *screening* fits: on records longer than ``screen_samples`` they use the first
``screen_samples`` samples, and at most ``screen_passes`` passes. The chosen structure is then fitted once more
with the full settings on the whole estimation record (``best_estimator_``; the screening's half-step input and pass
mode carry over, while ``R0="auto"`` is chosen again: the weight the start deserves depends on the record's length),
which with ``refit=True`` (in :data:`AUTO_SETTINGS`) also re-runs its chosen recipe over the hold-out: the hold-out
served to choose, and the final model uses every sample. With the default grid (3 orders x 4 output functions,
then 2 degrees x 2 or 3 finalists: 16 to 18 screening fits and one final fit) the search costs about 15 single fits
on records up to ``screen_samples`` samples; ``results_`` lists every fit with its time.
"""
from __future__ import annotations

import math
import time
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ident.base import BaseEstimator, as_2d, check_is_fitted, check_positive_int, check_same_length
from ident.rpem.estimator import AUTO_SETTINGS, OUTPUT_FUNCTIONS, RecursivePEM
from ident.rpem.regressors import polynomial_terms

__all__ = ["DEFAULT_DEGREES", "DEFAULT_ORDERS", "DEFAULT_OUTPUTS", "StructureSearch"]

#: The default grid: chain lengths, polynomial degrees of the right-hand side, static output functions.
DEFAULT_ORDERS: tuple[int, ...] = (1, 2, 3)
DEFAULT_DEGREES: tuple[int, ...] = (1, 2, 3)
DEFAULT_OUTPUTS: tuple[str, ...] = ("identity", "abs", "saturation", "polynomial")
#: Structure arguments a candidate sets; ``settings`` must not contain them.
_STRUCTURE_KEYS = ("n_states", "terms", "max_degrees", "total_degree", "output", "sampling_period")


class StructureSearch(BaseEstimator):
    """Choose the RPEM model structure (order, polynomial degree, output function) on an inner hold-out.

    ``StructureSearch(sampling_period=T).fit(u, y)`` fits a small grid of :class:`~ident.rpem.RecursivePEM`
    structures with the automatic settings and keeps the best on the hold-out (module docstring for the procedure,
    the grid and its cost). Use ``best_estimator_`` (a fitted ``RecursivePEM``: ``predict``, ``to_casadi``,
    ``save``) or the search itself, which forwards ``predict``, ``predict_k_step``, ``initial_state``, ``score``
    and ``to_casadi`` to it, so that ``ident.compare(search, u, y)`` works.

    Parameters
    ----------
    sampling_period : float
        Data sampling period T in seconds.
    orders : sequence of int
        Chain lengths ``n_states`` to try (each in 1..10).
    degrees : sequence of int
        Total polynomial degrees of the right-hand side to try (each in 1..5); the smallest is used in stage 1.
    outputs : sequence of str
        Static output functions to try (names of :data:`~ident.rpem.OUTPUT_FUNCTIONS`).
    n_finalists : int
        Orders of stage 1 (each with one output function) that go on to the larger degrees.
    max_terms : int
        Largest number of right-hand-side terms per output a candidate may have (the cost of a fit grows with its
        square); larger structures are skipped.
    tolerance : float
        FIT points (>= 0) within which a structure with fewer parameters is preferred to the best one.
    holdout : float
        Fraction of the record, at its end, that scores the candidates (in (0, 0.5)); passed to every fit.
    screen_samples : int or None
        Screening fits use at most this many samples, the first ones (None: the whole record).
    screen_passes : int or None
        Largest number of passes of a screening fit (None: those of the settings).
    settings : mapping, optional
        Settings of every fit (default :data:`~ident.rpem.AUTO_SETTINGS`); structure arguments (``n_states``,
        ``terms``, ``max_degrees``, ``total_degree``, ``output``, ``sampling_period``) are the search's and are
        refused here. Other ``RecursivePEM`` arguments (``input_transforms``, ``output_limits``, ``output_degree``,
        ``derivative_inputs``, ...) may be given.
    random_state : int
        Seed passed to every fit.

    Attributes
    ----------
    best_estimator_ : RecursivePEM
        The chosen structure fitted with the full settings on the whole estimation record (or its screened fit,
        see ``final_kept_``).
    best_params_ : dict
        ``{"n_states", "total_degree", "output"}`` of the chosen structure.
    best_score_ : float
        Its hold-out FIT (percent) in the screening.
    results_ : list of dict
        One row per candidate: ``stage`` (1, 2 or "final"), ``n_states``, ``total_degree``, ``output``,
        ``n_params`` (terms and output parameters, all outputs), ``holdout_fit`` (percent; -inf for a diverged
        model, None if skipped), ``fit_time_s``, ``note`` (warnings, skips, "chosen"). :meth:`table` prints it.
    n_screen_samples_ : int
        Samples used by the screening fits.
    final_kept_ : bool
        Whether ``best_estimator_`` is the final fit on the whole record (True) or the screened fit of the chosen
        structure (False: no final fit was needed, or the final fit scored worse than the screened one on the
        hold-out of the whole record, a recursion gone astray on the long record; ``results_`` says so).
    search_time_s_ : float
        Wall time of the whole search, final fit included.
    """

    def __init__(
        self,
        sampling_period: float = 1.0,
        orders: Sequence[int] = DEFAULT_ORDERS,
        degrees: Sequence[int] = DEFAULT_DEGREES,
        outputs: Sequence[str] = DEFAULT_OUTPUTS,
        n_finalists: int = 2,
        max_terms: int = 40,
        tolerance: float = 0.5,
        holdout: float = 0.2,
        screen_samples: int | None = 2048,
        screen_passes: int | None = None,
        settings: Mapping[str, Any] | None = None,
        random_state: int = 0,
    ) -> None:
        self.sampling_period = sampling_period
        self.orders = orders
        self.degrees = degrees
        self.outputs = outputs
        self.n_finalists = n_finalists
        self.max_terms = max_terms
        self.tolerance = tolerance
        self.holdout = holdout
        self.screen_samples = screen_samples
        self.screen_passes = screen_passes
        self.settings = settings
        self.random_state = random_state

    # ------------------------------------------------------------------ checks
    def _checked(self) -> tuple[list[int], list[int], list[str], dict[str, Any]]:
        def ints(name: str, values: Any, low: int, high: int) -> list[int]:
            if isinstance(values, (str, bytes)) or not isinstance(values, Sequence) or len(values) == 0:
                raise ValueError(f"{name} must be a non-empty sequence of integers, got {values!r}")
            out = []
            for v in values:
                if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not low <= int(v) <= high:
                    raise ValueError(f"{name} must hold integers in [{low}, {high}], got {v!r}")
                out.append(int(v))
            return sorted(set(out))

        orders = ints("orders", self.orders, 1, 10)
        degrees = ints("degrees", self.degrees, 1, 5)
        if isinstance(self.outputs, str) or not isinstance(self.outputs, Sequence) or len(self.outputs) == 0:
            raise ValueError(f"outputs must be a non-empty sequence of {list(OUTPUT_FUNCTIONS)}, got {self.outputs!r}")
        outputs = []
        for o in self.outputs:
            if o not in OUTPUT_FUNCTIONS:
                raise ValueError(f"outputs must hold names of {list(OUTPUT_FUNCTIONS)}, got {o!r}")
            if o not in outputs:
                outputs.append(o)
        check_positive_int("n_finalists", self.n_finalists)
        check_positive_int("max_terms", self.max_terms, what="(terms per output)")
        if self.screen_passes is not None:
            check_positive_int("screen_passes", self.screen_passes, what="(passes of a screening fit)")
        if self.screen_samples is not None:
            check_positive_int("screen_samples", self.screen_samples, minimum=100, what="samples")
        for name, value, low, high in (("tolerance", self.tolerance, 0.0, math.inf),
                                       ("holdout", self.holdout, 0.0, 0.5)):
            ok = not isinstance(value, (bool, str)) and isinstance(value, (int, float, np.floating, np.integer))
            if not ok or not math.isfinite(float(value)) or not low <= float(value) <= high or \
                    (name == "holdout" and not 0.0 < float(value) < 0.5):
                raise ValueError(f"{name} must be a finite number in "
                                 f"{'(0, 0.5)' if name == 'holdout' else '[0, inf)'}, got {value!r}")
        if isinstance(self.random_state, bool) or not isinstance(self.random_state, (int, np.integer)):
            raise ValueError(f"random_state must be an integer seed, got {self.random_state!r}")  # noqa: TRY004
        if not isinstance(self.settings, (Mapping, type(None))):
            raise ValueError(f"settings must be a mapping of RecursivePEM arguments, got {self.settings!r}")  # noqa: TRY004
        settings = dict(AUTO_SETTINGS if self.settings is None else self.settings)
        clash = sorted(set(settings) & set(_STRUCTURE_KEYS))
        if clash:
            raise ValueError(f"settings must not set {clash}: the search chooses the structure "
                             "(give the grid with orders/degrees/outputs, the sampling period as sampling_period)")
        unknown = sorted(set(settings) - set(RecursivePEM._get_param_names()))
        if unknown:
            raise ValueError(f"settings has unknown RecursivePEM argument(s) {unknown}")
        settings["holdout"] = float(self.holdout)
        settings["random_state"] = int(self.random_state)
        return orders, degrees, outputs, settings

    # ------------------------------------------------------------------ the search
    def _candidate(self, n: int, degree: int, output: str, settings: dict[str, Any]) -> RecursivePEM:
        return RecursivePEM(n_states=n, max_degrees=degree, total_degree=degree, output=output,
                            sampling_period=self.sampling_period, **settings)

    def _n_terms(self, n: int, degree: int, n_inputs: int) -> int:
        return len(polynomial_terms(n, n_inputs, degree, degree))

    def _run(self, est: RecursivePEM, u: np.ndarray, y: np.ndarray) -> tuple[RecursivePEM | None, float, str, float]:
        """Fit one candidate; returns (estimator or None, hold-out FIT, note, seconds)."""
        t0 = time.perf_counter()
        note = ""
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", RuntimeWarning)
            try:
                est.fit(u, y)
            except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
                return None, -math.inf, f"failed: {exc}"[:120], time.perf_counter() - t0
        msgs = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
        if msgs:
            note = "warned: " + msgs[0].split(";")[0][:100]
        score = est.holdout_fit_ if est.holdout_fit_ is not None else -math.inf
        return est, float(score), note, time.perf_counter() - t0

    def fit(self, u: Any, y: Any) -> StructureSearch:
        """Run the search on an estimation record (``u`` of shape ``(N, n_inputs)``, ``y`` of ``(N, n_outputs)``)."""
        t_start = time.perf_counter()
        orders, degrees, outputs, settings = self._checked()
        u2, y2 = as_2d("u", u), as_2d("y", y)
        check_same_length(u=u2, y=y2)
        N, m = u2.shape
        if N < 100:
            raise ValueError(f"u and y have {N} samples; the structure search needs at least 100 (its hold-out is "
                             f"{self.holdout:g} of the record)")
        n_screen = N if self.screen_samples is None else min(N, int(self.screen_samples))
        us, ys = u2[:n_screen], y2[:n_screen]
        n_passes = int(settings.get("n_passes", 1))
        screen_settings = {**settings, "n_passes": n_passes if self.screen_passes is None
                           else min(n_passes, int(self.screen_passes))}
        d = y2.shape[1]
        q_out = {"identity": 0, "abs": 1, "saturation": 2,
                 "polynomial": int(settings.get("output_degree", 3))}
        rows: list[dict[str, Any]] = []
        fitted: dict[tuple[int, int, str], RecursivePEM] = {}

        def attempt(stage: int, n: int, degree: int, output: str, fixed: dict[str, Any] | None = None) -> None:
            n_terms = self._n_terms(n, degree, m)
            row = {"stage": stage, "n_states": n, "total_degree": degree, "output": output,
                   "n_params": d * (n_terms + q_out[output]), "holdout_fit": None, "fit_time_s": 0.0, "note": ""}
            if n_terms > int(self.max_terms):
                row["note"] = f"skipped: {n_terms} terms > max_terms={int(self.max_terms)}"
            else:
                est, score, note, secs = self._run(self._candidate(n, degree, output,
                                                                    {**screen_settings, **(fixed or {})}), us, ys)
                row.update(holdout_fit=score, fit_time_s=round(secs, 2), note=note)
                if est is not None:
                    fitted[(n, degree, output)] = est
            rows.append(row)

        low = degrees[0]
        for n in orders:
            for output in outputs:
                attempt(1, n, low, output)
        # each order goes on with its simplest output function among those within tolerance of that order's best
        # (the parsimony rule of the final choice, applied per order: near-ties are noise on a short hold-out);
        # the n_finalists orders with the best hold-out FIT go on to the larger degrees
        per_order: list[tuple[float, int, str]] = []
        for n in orders:
            scored_n = [r for r in rows if r["n_states"] == n and r["holdout_fit"] is not None
                        and np.isfinite(r["holdout_fit"])]
            if scored_n:
                top_n = max(r["holdout_fit"] for r in scored_n)
                pick = min((r for r in scored_n if r["holdout_fit"] >= top_n - float(self.tolerance)),
                           key=lambda r: (r["n_params"], -r["holdout_fit"]))
                per_order.append((top_n, n, pick["output"]))
        per_order.sort(key=lambda t: -t[0])
        finalists = [(n, output) for _, n, output in per_order[:int(self.n_finalists)]]
        if per_order and "identity" in outputs and (per_order[0][1], "identity") not in finalists \
                and (per_order[0][1], low, "identity") in fitted:
            # every output function contains the identity (eta = 0, wide limits, a positive signal): with linear
            # dynamics another output may win by mimicking a nonlinearity of the dynamics, which the larger degrees
            # model directly, so the identity at the best order always goes on
            finalists.append((per_order[0][1], "identity"))
        for n, output in finalists:
            # the half-step input describes the input between samples, not the structure: keep the finalist's
            hs = fitted[(n, low, output)].half_step_input_
            for degree in degrees[1:]:
                attempt(2, n, degree, output, {"half_step_input": hs})
        scored = [r for r in rows if r["holdout_fit"] is not None and np.isfinite(r["holdout_fit"])]
        if not scored:
            raise ValueError("no candidate structure could be fitted (every fit failed or diverged); see "
                             "results_ / table() of this search: " + "; ".join(r["note"] for r in rows)[:300])
        top = max(r["holdout_fit"] for r in scored)
        near = [r for r in scored if r["holdout_fit"] >= top - float(self.tolerance)]
        choice = min(near, key=lambda r: (r["n_params"], -r["holdout_fit"]))
        choice["note"] = (choice["note"] + "; chosen").lstrip("; ")
        key = (choice["n_states"], choice["total_degree"], choice["output"])
        self.best_params_ = {"n_states": key[0], "total_degree": key[1], "output": key[2]}
        self.best_score_ = float(choice["holdout_fit"])
        same = n_screen == N and screen_settings["n_passes"] == settings.get("n_passes", 1)
        self.final_kept_ = False
        if same:
            self.best_estimator_ = fitted[key]
        else:
            chosen = fitted[key]  # its half-step input and pass mode carry over to the final fit (R0 is chosen again)
            final = {**settings, "half_step_input": chosen.half_step_input_, "pass_mode": chosen.pass_mode_}
            est, score, note, secs = self._run(self._candidate(*key, final), u2, y2)
            # the final fit may go astray on the long record (a recursion that diverges over many more samples):
            # the screened model and the final one are both scored on the whole record's hold-out (the last
            # `holdout` of the estimation record; the screening never saw it, the final fit with refit=True did),
            # and the final one is kept unless it scores worse there
            tail = N - round(float(self.holdout) * N)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                screened = float(chosen.score(u2[tail:], y2[tail:]))
                whole = -math.inf if est is None else float(est.score(u2[tail:], y2[tail:]))
            keep_final = np.isfinite(whole) and not whole < screened
            rows.append({"stage": "final", "n_states": key[0], "total_degree": key[1], "output": key[2],
                         "n_params": choice["n_params"], "holdout_fit": score, "fit_time_s": round(secs, 2),
                         "note": (note or "whole record, full settings") + (
                             "" if keep_final else f"; not kept: hold-out FIT {whole:.1f} % < the screened "
                                                   f"model's {screened:.1f} %")})
            self.best_estimator_ = est if keep_final else chosen
            self.final_kept_ = bool(keep_final)
        self.results_ = rows
        self.n_screen_samples_ = n_screen
        self.n_inputs_, self.n_outputs_ = m, d
        self.search_time_s_ = time.perf_counter() - t_start
        return self

    # ------------------------------------------------------------------ report
    def table(self) -> str:
        """``results_`` as a text table, one line per candidate."""
        check_is_fitted(self, "results_")
        header = f"{'stage':>5} {'n':>2} {'deg':>3} {'output':<10} {'params':>6} {'hold-out FIT':>12} {'time s':>7}"
        lines = [header + "  note"]
        for r in self.results_:
            h = r["holdout_fit"]
            hs = "-" if h is None else ("diverged" if not np.isfinite(h) else f"{h:.1f} %")
            lines.append(f"{r['stage']!s:>5} {r['n_states']:>2} {r['total_degree']:>3} {r['output']:<10} "
                         f"{r['n_params']:>6} {hs:>12} {r['fit_time_s']:>7.1f}  {r['note']}")
        return "\n".join(lines)

    # ------------------------------------------------------------------ the chosen model
    def _best(self) -> RecursivePEM:
        check_is_fitted(self, "best_estimator_")
        return self.best_estimator_

    def predict(self, u: Any, y0: Any | None = None, *, x0: Any | None = None) -> np.ndarray:
        """:meth:`RecursivePEM.predict` of the chosen model."""
        return self._best().predict(u, y0, x0=x0)

    def predict_k_step(self, u: Any, y: Any, k: int) -> np.ndarray:
        """:meth:`RecursivePEM.predict_k_step` of the chosen model."""
        return self._best().predict_k_step(u, y, k)

    def initial_state(self, u: Any, y: Any, n_samples: int | None = None) -> np.ndarray:
        """:meth:`RecursivePEM.initial_state` of the chosen model."""
        return self._best().initial_state(u, y, n_samples)

    def score(self, u: Any, y: Any) -> float:
        """:meth:`RecursivePEM.score` of the chosen model (simulation FIT, percent)."""
        return self._best().score(u, y)

    def to_casadi(self) -> Any:
        """:meth:`RecursivePEM.to_casadi` of the chosen model."""
        return self._best().to_casadi()

    def save(self, path: Any) -> Any:
        """Save the chosen model (a ``RecursivePEM`` file: read it back with ``RecursivePEM.load``)."""
        return self._best().save(path)

    @classmethod
    def load(cls, path: Any) -> Any:
        """Not available: a search saves its chosen model, which ``RecursivePEM.load(path)`` reads."""
        raise ValueError(f"StructureSearch.load: a search saves its chosen model; read {path!s} with "
                         "RecursivePEM.load")
