"""The identify-then-control loop's pieces: black-box identification for control, held-out cycles, the gap closed.

1. Excitation experiments on the plant (open loop, random cycles; never the held-out cycles): the grey-box model's
   records (:func:`control.factory.greybox_record`) and :func:`black_box_excitation`, a record with sustained
   over-dosing so that NH3 slip is excited too (black-box models).
2. :func:`identify_black_box`: a linear state-space model (N4SID), RPEM (2nd-order chain per output, the 9-term
   structure of Paper III) and, optionally, Hammerstein-Wiener (Wiener with output saturation, one per output) on
   normalised data, saved beside each other; validation FIT of each output on held-out excitation data (the WHTC,
   another seed).
3. :func:`loop_controller`: the NMPC on each identified model (:func:`control.factory.black_box_mpc`,
   :func:`control.factory.identified_mpc`), the oracle, the baselines and the shipped RL policies, by name.
4. :func:`held_out` cycles and :func:`gap_closed`: the fraction of the look-up-table-to-oracle gap in tailpipe NOx
   that the NMPC on each identified model closes, counted within the Euro VI slip limit only.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from scr_env.constants import EURO_VI_NH3_SLIP_LIMIT_PPM

__all__ = ["BLACK_BOX", "black_box_excitation", "gap_closed", "held_out", "identify_black_box", "load_black_box",
           "loop_controller"]

#: the black-box model kinds of the loop
BLACK_BOX = ("linear", "rpem", "hammerstein_wiener")
EXCITATION_SEED = 3  # random cycle of the black-box excitation record (held-out cycles are WHTC/WHSC)
VALIDATION_SEED = 99  # sensor noise and excitation seed of the validation record (on the WHTC)
QUICK_SEGMENT_S = 600.0  # s of each held-out cycle in quick mode
#: mean NH3 slip limit [ppm] within which a gap counts as closed (Euro VI)
SLIP_LIMIT_PPM = EURO_VI_NH3_SLIP_LIMIT_PPM


def black_box_excitation(cycle: str, seed: int, duration_s: float = 3600.0) -> Any:
    """Open-loop record with sustained over-dosing phases (ANR 0.1 to 2, held 20-200 s): NH3 slip is excited."""
    from ident.excitation import RandomSteps
    from ident.plant_data import excitation_dataset

    kw = {"random_cycle_duration_s": duration_s} if cycle == "random" else {}
    return excitation_dataset(cycle, seed=seed, base_anr=1.0, excitation=RandomSteps(-0.9, 1.0, 20.0, 200.0), **kw)


def held_out(quick: bool) -> list[Any]:
    """The held-out cycles (ExhaustTraces): hot WHTC and WHSC, or the WHTC's first :data:`QUICK_SEGMENT_S`
    seconds (named ``whtc_0-600s``)."""
    from control.evaluation import cycle_segment
    from scr_env.cycles import load_cycle

    if quick:
        return [cycle_segment("whtc", QUICK_SEGMENT_S, name=f"whtc_0-{int(QUICK_SEGMENT_S)}s")]
    return [load_cycle(name, dt=0.5) for name in ("whtc", "whsc")]


def identify_black_box(out: Path, include_hw: bool) -> dict[str, Any]:
    """Fit the black-box models on normalised data; save them (JSON + NPZ) to ``out``; return their paths, the
    normalisation, the data description and the validation FIT [%] and SD [ppm] per output. A model whose fit
    fails is reported (``{"error": ...}``), not raised."""
    from ident.hammerstein_wiener import HammersteinWiener, Saturation
    from ident.io import save_model
    from ident.linear import N4SID
    from ident.metrics import fit_percent
    from ident.preprocessing import Normalizer
    from ident.rpem import SCR_PAPER3_LINEAR_TERMS, RecursivePEM
    from ident.stack import OutputStack

    est = black_box_excitation("random", EXCITATION_SEED)
    val = black_box_excitation("whtc", VALIDATION_SEED)
    nu, ny = Normalizer().fit(est.u), Normalizer().fit(est.y)
    u, y, uv, yv = nu.transform(est.u), ny.transform(est.y), nu.transform(val.u), ny.transform(val.y)
    w_min = -ny.mean_ / ny.scale_  # zero ppm in normalised units: the output saturation of Papers III/IV
    candidates: dict[str, Any] = {
        "linear": lambda: N4SID(order=4),
        "rpem": lambda: RecursivePEM(n_states=2, terms=SCR_PAPER3_LINEAR_TERMS, sampling_period=est.dt, alpha=1.5,
                                     init="kalman", n_passes=3,
                                     output_limits=[(float(w), np.inf) for w in w_min]),
    }
    if include_hw:
        candidates["hammerstein_wiener"] = lambda: OutputStack(
            [HammersteinWiener(output_block=Saturation(lower=float(w_min[i])), max_nfev=30) for i in range(3)])
    info: dict[str, Any] = {"data": {"estimation": est.meta, "validation": val.meta},
                            "input_mean": nu.mean_.tolist(), "input_scale": nu.scale_.tolist(),
                            "output_mean": ny.mean_.tolist(), "output_scale": ny.scale_.tolist(), "models": {}}
    for name, make in candidates.items():
        t0 = time.perf_counter()
        try:
            model = make().fit(u, y)
        except Exception as exc:  # noqa: BLE001  (an identification failure is a result, reported, not a crash)
            info["models"][name] = {"error": f"{type(exc).__name__}: {exc}"}
            continue
        yp = model.predict(uv)
        fits = {n: float(fit_percent(yv[:, i], yp[:, i])) for i, n in enumerate(val.output_names)}
        entry: dict[str, Any] = {"fit_seconds": time.perf_counter() - t0, "validation_fit_percent": fits,
                                 "validation_sd_ppm": {n: float(val.y[:, i].std())
                                                       for i, n in enumerate(val.output_names)}}
        if isinstance(model, OutputStack):
            entry["paths"] = [str(save_model(m, out / f"model_{name}_{i}")) for i, m in enumerate(model.models_)]
        else:
            entry["paths"] = [str(save_model(model, out / f"model_{name}"))]
        info["models"][name] = entry
    return info


def load_black_box(name: str, info: dict[str, Any]) -> Any:
    """The black-box model ``name`` saved by :func:`identify_black_box` (an OutputStack if saved per output)."""
    from ident.io import load_model
    from ident.stack import OutputStack

    models = [load_model(p) for p in info["models"][name]["paths"]]
    if len(models) == 1:
        return models[0]
    stack = OutputStack([None] * len(models))
    stack.models_ = models
    return stack


def loop_controller(name: str, greybox: Any, black_box: dict[str, Any] | None, quick: bool) -> Any:
    """A policy of the loop by name: ``lookup_table``, ``pi``, ``mpc_oracle``, ``mpc_greybox`` (the benchmark's
    ``mpc_identified`` on the fitted grey-box model ``greybox``), ``mpc_<kind>`` for a black-box model of
    :func:`identify_black_box` (``black_box``: its returned info), or a shipped RL policy."""
    from control.factory import black_box_mpc, identified_mpc, make_controller

    if name == "mpc_greybox":
        return identified_mpc(greybox, quick)
    if name.startswith("mpc_") and name != "mpc_oracle":
        if black_box is None or name[4:] not in black_box.get("models", {}):
            raise ValueError(f"{name}: no identified black-box model {name[4:]!r}")
        bb = black_box
        return black_box_mpc(load_black_box(name[4:], bb), bb["input_mean"], bb["input_scale"], bb["output_mean"],
                             bb["output_scale"], quick)
    return make_controller(name, None, quick)


def gap_closed(kpis: dict[str, dict[str, dict[str, float]]]) -> tuple[dict[str, dict[str, float]], list[dict]]:
    """``{model: {cycle: (LUT - MPC_model) / (LUT - oracle)}}`` in tailpipe NOx g/kWh, and the excluded entries.

    A model/cycle pair counts only if that NMPC (and the oracle) kept the mean NH3 slip within
    :data:`SLIP_LIMIT_PPM`: closing the NOx gap by slipping ammonia is not closing it "at the same slip limit". The
    excluded pairs are returned with their raw fraction and slip, so nothing is hidden.
    """
    out: dict[str, dict[str, float]] = {}
    excluded: list[dict] = []
    for cycle, ctrl in kpis.items():
        if "lookup_table" not in ctrl or "mpc_oracle" not in ctrl:
            continue
        lut = ctrl["lookup_table"]["tailpipe_nox_g_per_kwh"]
        orc = ctrl["mpc_oracle"]["tailpipe_nox_g_per_kwh"]
        oracle_ok = ctrl["mpc_oracle"].get("mean_nh3_slip_ppm", float("inf")) <= SLIP_LIMIT_PPM
        for name, row in ctrl.items():
            if not name.startswith("mpc_") or name == "mpc_oracle":
                continue
            gap = lut - orc
            val = (lut - row["tailpipe_nox_g_per_kwh"]) / gap if gap > 0 else float("nan")
            slip = row.get("mean_nh3_slip_ppm", float("inf"))
            if oracle_ok and slip <= SLIP_LIMIT_PPM and np.isfinite(val):
                out.setdefault(name[4:], {})[cycle] = float(val)
            else:
                reason = "oracle above the slip limit" if not oracle_ok else (
                    "no gap (oracle not better than the look-up table)" if not np.isfinite(val)
                    else f"mean NH3 slip {slip:.1f} ppm > {SLIP_LIMIT_PPM:.0f} ppm")
                excluded.append({"model": name[4:], "cycle": cycle, "raw_fraction": float(val),
                                 "mean_nh3_slip_ppm": float(slip), "reason": reason})
    return out, excluded
