"""Identification for control of the SCR dosing loop (issue 18, research prototype): signal features of measured
quantities, control-relevant excitation and closed-loop identification records over many random cycles.

Features (:class:`FeatureMap`) are static transforms of *measured* signals only -- the dose command and the
engine-out disturbances (inlet NOx, inlet temperature, exhaust flow) -- written once for numpy and CasADi:

========== ========= ===================================================================================
name       unit      meaning
========== ========= ===================================================================================
nox_ppm    ppm       inlet (engine-out) NOx
urea       g/min     urea dose (AdBlue g/s * 60 * 0.325, the thesis' unit)
temp_k     K         SCR-inlet temperature
flow       mol/s     exhaust flow
exp_t      -         exp(-a / T_in), a = 1e4 K scaled by exp(a / 550 K) (Paper III's u3*, order one)
nox_flow   mmol/s    inlet NOx molar flow, nox_ppm * 1e-6 * flow * 1e3
nh3_flow   mmol/s    NH3 dosed, AdBlue g/s * NH3_MOL_PER_G_ADBLUE * 1e3 (before decomposition)
surplus    mmol/s    stoichiometric surplus, nh3_flow - nox_flow (the issue's "NH3 dosed minus NOx flow")
anr        -         nh3_flow / (nox_flow + 0.05 mmol/s), the ammonia-to-NOx ratio, bounded at idle
nh3_ppm    ppm       NH3 dosed as a concentration in the exhaust, nh3_flow / flow (before decomposition)
surplus_ppm ppm      nh3_ppm - nox_ppm
log_deficit -        log(deficit / (nox_ppm + 20 ppm) + 0.01), deficit = the inlet NOx the dose cannot reduce,
                     smooth max(nox_ppm - nh3_ppm, 0) (the NOx slip ratio of a fast catalyst, in the NOx output's
                     log representation)
log_excess  -        log(excess + 1 ppm), excess = smooth max(nh3_ppm - nox_ppm, 0) [ppm] (the NH3 a fast catalyst
                     without storage would slip, in the NH3 output's log representation)
========== ========= ===================================================================================

The last two are the logarithms of the positive and negative parts of the stoichiometric surplus: with the outputs
in log form, a model linear in ``surplus_ppm`` predicts that each extra ppm of NH3 removes a fixed *fraction* of the
remaining NOx, so the marginal NOx benefit of dosing vanishes as conversion rises, while on a hot catalyst it stays
one ppm per ppm until the NOx is used up (and the excess then slips). These two features let a linear or
polynomial model express that spill-over (the issue's "stoichiometric-surplus input") without a balance.

None of them is a balance or a rate law: they are the inputs of the black-box models, like the thesis' exp(-a/T).
Nothing here integrates a signal (an integral of the surplus with desorption would be the grey-box's storage
balance, outside the black-box boundary of issue 18, section 5).

Output representations (:data:`OUTPUT_KINDS`): the tailpipe NOx in ppm, or as the NOx *slip ratio*
``nox_out / (nox_in + eps)`` (a transform of two measured signals; ``eps`` = :data:`RATIO_EPS_PPM`); the NH3 slip in
ppm.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from scr_env.constants import NH3_MOL_PER_G_ADBLUE

#: g/min of urea per g/s of AdBlue (AUS 32)
UREA_G_MIN_PER_ADBLUE_G_S = 60.0 * 0.325
#: Paper III's temperature transform exp(-a/T) [a in K]; scaled to order one at 550 K [chosen]
EXP_A_K = 1.0e4
EXP_T_REF_K = 550.0
#: NOx flow added in the ANR denominator [mmol/s] (about 10 ppm at 5 mol/s: keeps the ratio bounded at idle) [chosen]
ANR_EPS_MMOL_S = 0.05
#: inlet NOx added in the denominator of the NOx slip ratio [ppm] [chosen]
RATIO_EPS_PPM = 20.0
#: floors of the logarithmic outputs: NOx slip ratio [-] and NH3 slip [ppm] (below any sensor's resolution) [chosen]
LOG_RATIO_FLOOR = 1e-4
LOG_NH3_FLOOR_PPM = 0.01

FEATURES = ("nox_ppm", "urea", "temp_k", "flow", "exp_t", "nox_flow", "nh3_flow", "surplus", "anr", "nh3_ppm",
            "surplus_ppm", "log_deficit", "log_excess")
#: smoothing of the max(., 0) of the deficit / excess features [ppm]: 0.5 (v + sqrt(v^2 + e^2)) is within e/2 of it,
#: and smooth for the NMPC's derivatives [chosen]
SURPLUS_SMOOTH_PPM = 2.0
#: floors of the deficit ratio [-] and of the excess [ppm] inside the logarithms of log_deficit / log_excess [chosen:
#: a NOx slip ratio of 1 %, about the best conversion in the identification data; 1 ppm, the NH3 sensor's noise]
DEFICIT_RATIO_FLOOR = 0.01
EXCESS_FLOOR_PPM = 1.0
OUTPUT_KINDS = ("ppm", "ratio", "logratio")
NH3_KINDS = ("ppm", "log")


def _is_sym(*xs: Any) -> bool:
    return any(isinstance(x, (ca.SX, ca.MX, ca.DM)) for x in xs)


def smooth_positive_part(v: Any, eps: float) -> Any:
    """A smooth max(v, 0): 0.5 (v + sqrt(v^2 + eps^2)), within eps/2 of it and differentiable for the NMPC;
    ``v`` a number, a numpy array or a CasADi expression."""
    sqrt = ca.sqrt if _is_sym(v) else np.sqrt
    return 0.5 * (v + sqrt(v * v + eps * eps))


def feature_values(name: str, adblue_g_s: Any, nox_ppm: Any, temp_k: Any, flow: Any) -> Any:
    """One feature (module docstring) from the dose [g/s] and the disturbances (numpy arrays, floats or CasADi)."""
    sym = _is_sym(adblue_g_s, nox_ppm, temp_k, flow)
    exp = ca.exp if sym else np.exp
    fmax = ca.fmax if sym else np.maximum
    nox_flow = fmax(nox_ppm, 0.0) * 1e-6 * flow * 1e3
    nh3_flow = adblue_g_s * NH3_MOL_PER_G_ADBLUE * 1e3
    surplus_ppm = nh3_flow / fmax(flow, 0.1) * 1e3 - fmax(nox_ppm, 0.0)
    if name == "nox_ppm":
        return nox_ppm
    if name == "urea":
        return adblue_g_s * UREA_G_MIN_PER_ADBLUE_G_S
    if name == "temp_k":
        return temp_k
    if name == "flow":
        return flow
    if name == "exp_t":
        return exp(-EXP_A_K / fmax(temp_k, 200.0) + EXP_A_K / EXP_T_REF_K)
    if name == "nox_flow":
        return nox_flow
    if name == "nh3_flow":
        return nh3_flow
    if name == "surplus":
        return nh3_flow - nox_flow
    if name == "anr":
        return nh3_flow / (nox_flow + ANR_EPS_MMOL_S)
    if name == "nh3_ppm":
        return nh3_flow / fmax(flow, 0.1) * 1e3
    if name == "surplus_ppm":
        return surplus_ppm
    if name in ("log_deficit", "log_excess"):
        log = ca.log if sym else np.log
        part = smooth_positive_part(surplus_ppm if name == "log_excess" else -surplus_ppm, SURPLUS_SMOOTH_PPM)
        if name == "log_excess":
            return log(part + EXCESS_FLOOR_PPM)
        return log(part / (fmax(nox_ppm, 0.0) + RATIO_EPS_PPM) + DEFICIT_RATIO_FLOOR)
    raise ValueError(f"unknown feature {name!r}; known: {FEATURES}")


@dataclass(frozen=True)
class FeatureMap:
    """The model inputs as named features of the measured signals (module docstring)."""

    names: tuple[str, ...] = ("nox_ppm", "urea", "temp_k", "flow")

    def __post_init__(self) -> None:
        for n in self.names:
            if n not in FEATURES:
                raise ValueError(f"unknown feature {n!r}; known: {FEATURES}")

    def __len__(self) -> int:
        return len(self.names)

    def from_signals(self, adblue_g_s: Any, nox_ppm: Any, temp_k: Any, flow: Any) -> list:
        """Feature list (CasADi or numpy) from the dose [g/s] and the disturbances."""
        return [feature_values(n, adblue_g_s, nox_ppm, temp_k, flow) for n in self.names]

    def from_record(self, u: np.ndarray) -> np.ndarray:
        """(n, len(names)) features from a :mod:`ident.plant_data` input record (inlet NOx ppm, urea g/min, T K,
        flow mol/s)."""
        u = np.asarray(u, dtype=float)
        adblue = u[:, 1] / UREA_G_MIN_PER_ADBLUE_G_S
        return np.column_stack(self.from_signals(adblue, u[:, 0], u[:, 2], u[:, 3]))


def nox_output(kind: str, nox_out_ppm: Any, nox_in_ppm: Any) -> Any:
    """The NOx output representation of ``kind`` from tailpipe and inlet NOx [ppm]."""
    if kind == "ppm":
        return nox_out_ppm
    if kind in ("ratio", "logratio"):
        sym = _is_sym(nox_out_ppm, nox_in_ppm)
        fmax = ca.fmax if sym else np.maximum
        r = fmax(nox_out_ppm, 0.0) / (fmax(nox_in_ppm, 0.0) + RATIO_EPS_PPM)
        return r if kind == "ratio" else (ca.log if sym else np.log)(r + LOG_RATIO_FLOOR)
    raise ValueError(f"unknown NOx output kind {kind!r}; known: {OUTPUT_KINDS}")


def nox_ppm_from_output(kind: str, y: Any, nox_in_ppm: Any) -> Any:
    """Inverse of :func:`nox_output`: tailpipe NOx [ppm] from the representation ``y``."""
    if kind == "ppm":
        return y
    if kind in ("ratio", "logratio"):
        sym = _is_sym(y, nox_in_ppm)
        fmax = ca.fmax if sym else np.maximum
        r = y if kind == "ratio" else (ca.exp if sym else np.exp)(y) - LOG_RATIO_FLOOR
        return r * (fmax(nox_in_ppm, 0.0) + RATIO_EPS_PPM)
    raise ValueError(f"unknown NOx output kind {kind!r}; known: {OUTPUT_KINDS}")


def nh3_output(kind: str, nh3_ppm: Any) -> Any:
    """The NH3 output representation of ``kind`` (``"ppm"`` or ``"log"``: log(ppm + floor))."""
    if kind == "ppm":
        return nh3_ppm
    if kind == "log":
        sym = _is_sym(nh3_ppm)
        return (ca.log if sym else np.log)((ca.fmax if sym else np.maximum)(nh3_ppm, 0.0) + LOG_NH3_FLOOR_PPM)
    raise ValueError(f"unknown NH3 output kind {kind!r}; known: {NH3_KINDS}")


def nh3_ppm_from_output(kind: str, y: Any) -> Any:
    """Inverse of :func:`nh3_output`."""
    if kind == "ppm":
        return y
    if kind == "log":
        return (ca.exp if _is_sym(y) else np.exp)(y) - LOG_NH3_FLOOR_PPM
    raise ValueError(f"unknown NH3 output kind {kind!r}; known: {NH3_KINDS}")


# ------------------------------------------------------------------------------------------------- records
@dataclass
class Record:
    """One identification record: plant-data inputs ``u`` (n, 4: inlet NOx ppm, urea g/min, T K, flow mol/s),
    outputs ``y`` (n, 3: tailpipe NOx ppm, NH3 ppm, NOx sensor ppm), the NH3 sensor ``nh3_sensor`` (n,), and
    ``meta`` (cycle, seed, dosing)."""

    u: np.ndarray
    y: np.ndarray
    nh3_sensor: np.ndarray
    dt: float
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.u)


def random_family(cycle: str) -> str:
    """``cycle`` checked: a seeded random-cycle family of :data:`scr_env.cycles.RANDOM_CYCLES` (records come from
    seeded random cycles only; never the held-out WHTC/WHSC)."""
    from scr_env.cycles import RANDOM_CYCLES, is_random_cycle

    if not is_random_cycle(cycle):
        raise ValueError(f"cycle must be a random-cycle family {sorted(RANDOM_CYCLES)}, got {cycle!r}")
    return str(cycle)


def _record_from_trajectory(tr: Any, meta: dict) -> Record:
    s = tr.signals
    u = np.column_stack([s["inlet_nox_ppm"], s["adblue_g_s"] * UREA_G_MIN_PER_ADBLUE_G_S,
                         s["inlet_temperature_k"], s["exhaust_flow_mol_s"]])
    y = np.column_stack([s["tailpipe_nox_ppm"], s["tailpipe_nh3_ppm"], s["nox_sensor_ppm"]])
    return Record(u=u, y=y, nh3_sensor=np.asarray(s["nh3_sensor_ppm"]).copy(), dt=float(tr.dt), meta=meta)


@dataclass(frozen=True)
class ControlRelevantDosing:
    """Open-loop dosing for identification in the region the NMPC will use (issue 18, "control-relevant
    excitation"): the feedforward on the measured upstream NOx flow at an ANR that holds random levels in
    ``anr_range`` for ``hold_s`` seconds (so the store fills towards the slip edge and drains), with over-dosing
    bursts of ANR ``burst_anr`` for ``burst_s`` seconds starting with probability ``burst_rate_per_s`` per second
    (the slip edge is crossed), plus a floor ``floor_g_s`` of AdBlue dosed with probability 1/2 per hold (NH3 at idle).
    All levels are drawn from the record's seed, independently of the measurements (open loop)."""

    anr_range: tuple[float, float] = (0.8, 1.3)
    hold_s: tuple[float, float] = (20.0, 120.0)
    burst_anr: tuple[float, float] = (2.0, 3.5)
    burst_s: tuple[float, float] = (4.0, 20.0)
    burst_rate_per_s: float = 1.0 / 150.0
    floor_g_s: float = 0.05

    def anr_sequence(self, n: int, dt: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """(ANR per step, AdBlue floor per step [g/s])."""
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xD05E]))
        anr = np.empty(n)
        floor = np.zeros(n)
        i = 0
        while i < n:
            k = max(1, round(rng.uniform(*self.hold_s) / dt))
            anr[i:i + k] = rng.uniform(*self.anr_range)
            floor[i:i + k] = self.floor_g_s if rng.random() < 0.5 else 0.0
            i += k
        t = 0
        while t < n:
            gap = rng.exponential(1.0 / self.burst_rate_per_s) if self.burst_rate_per_s > 0 else np.inf
            t += max(1, round(gap / dt))
            if t >= n:
                break
            k = max(1, round(rng.uniform(*self.burst_s) / dt))
            anr[t:t + k] = rng.uniform(*self.burst_anr)
            t += k
        return anr, floor


@dataclass(frozen=True)
class EdgeSeekingDosing:
    """A relay experiment around the slip edge (issue 18, control-relevant excitation): the feedforward at a "fill"
    ANR drawn from ``fill_anr`` until the tailpipe NH3 sensor reads more than a threshold drawn from ``slip_ppm``
    (the store has reached the spill-over edge), then a "drain" ANR from ``drain_anr`` for a time drawn from
    ``drain_s`` or until the NOx sensor reads more than a fraction drawn from ``breakthrough`` of the upstream NOx
    (the store is empty), then fill again; every level, threshold and duration is drawn anew at each switch from
    the record's seed. At most ``max_fill_s`` of filling in a row (hot catalyst: the edge may be unreachable).
    The switching reads the sensors (a relay feedback, Astrom and Hagglund 1984): the data stay near the edges
    the NMPC will work at, with the randomised levels as the dither."""

    fill_anr: tuple[float, float] = (1.1, 2.5)
    drain_anr: tuple[float, float] = (0.0, 0.9)
    slip_ppm: tuple[float, float] = (3.0, 40.0)
    drain_s: tuple[float, float] = (10.0, 200.0)
    breakthrough: tuple[float, float] = (0.05, 0.3)
    max_fill_s: float = 400.0


def edge_seeking_record(seed: int, dosing: EdgeSeekingDosing | None = None, duration_s: float | None = None,
                        dt: float = 0.5, cycle: str = "random") -> Record:
    """Roll the plant (``UreaSCREnv(cycle=cycle, nh3_sensor=True)``, reset seed ``seed``; ``cycle`` one of the
    seeded random families :data:`scr_env.cycles.RANDOM_CYCLES`) out under :class:`EdgeSeekingDosing` and return the
    record."""
    from ident.plant_data import feedforward_adblue_g_s
    from scr_env.envs.urea_scr import UreaSCREnv
    from scr_env.rollout import rollout

    dz = dosing or EdgeSeekingDosing()
    kw = {} if duration_s is None else {"random_cycle_duration_s": float(duration_s)}
    env = UreaSCREnv(cycle=random_family(cycle), dt=dt, nh3_sensor=True, **kw)
    env.reset(seed=seed)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xED6E]))
    max_rate = env.max_rate_g_s
    st = {"mode": "fill", "anr": rng.uniform(*dz.fill_anr), "thr": rng.uniform(*dz.slip_ppm), "t": 0.0,
          "limit": dz.max_fill_s, "bt": rng.uniform(*dz.breakthrough)}

    def switch(mode: str) -> None:
        st["mode"], st["t"] = mode, 0.0
        if mode == "fill":
            st["anr"], st["thr"], st["limit"] = rng.uniform(*dz.fill_anr), rng.uniform(*dz.slip_ppm), dz.max_fill_s
        else:
            st["anr"], st["limit"], st["bt"] = rng.uniform(*dz.drain_anr), rng.uniform(*dz.drain_s), \
                rng.uniform(*dz.breakthrough)

    def policy(obs: np.ndarray, k: int) -> np.ndarray:
        st["t"] += dt
        if st["mode"] == "fill" and (obs[5] > st["thr"] or st["t"] > st["limit"]):
            switch("drain")
        elif st["mode"] == "drain" and (st["t"] > st["limit"] or (obs[0] > 50 and obs[3] > st["bt"] * obs[0])):
            switch("fill")
        rate = feedforward_adblue_g_s(float(obs[0]), float(obs[2]), float(st["anr"]))
        return np.array([2.0 * min(rate, max_rate) / max_rate - 1.0], dtype=np.float32)

    tr = rollout(policy, env=env, seed=seed)
    return _record_from_trajectory(tr, {"kind": "edge_seeking", "cycle": tr.cycle, "seed": int(seed),
                                        "dosing": repr(dz)})


def open_loop_record(seed: int, dosing: ControlRelevantDosing | None = None, duration_s: float | None = None,
                     dt: float = 0.5, cycle: str = "random") -> Record:
    """Roll the plant (``UreaSCREnv(cycle=cycle, nh3_sensor=True)``, reset seed ``seed``: random cycle of the family
    ``cycle`` (:data:`scr_env.cycles.RANDOM_CYCLES`) and sensor noise) out under :class:`ControlRelevantDosing`
    (default design) and return the record."""
    from ident.plant_data import feedforward_adblue_g_s
    from scr_env.envs.urea_scr import UreaSCREnv
    from scr_env.rollout import rollout

    dosing = dosing or ControlRelevantDosing()
    kw = {} if duration_s is None else {"random_cycle_duration_s": float(duration_s)}
    env = UreaSCREnv(cycle=random_family(cycle), dt=dt, nh3_sensor=True, **kw)
    _, info = env.reset(seed=seed)
    n = int(info["n_steps"])
    anr, floor = dosing.anr_sequence(n, dt, seed)
    max_rate = env.max_rate_g_s

    def policy(obs: np.ndarray, k: int) -> np.ndarray:
        rate = feedforward_adblue_g_s(float(obs[0]), float(obs[2]), float(anr[k])) + floor[k]
        return np.array([2.0 * min(rate, max_rate) / max_rate - 1.0], dtype=np.float32)

    tr = rollout(policy, env=env, seed=seed)
    return _record_from_trajectory(tr, {"kind": "open_loop", "cycle": tr.cycle, "seed": int(seed),
                                        "dosing": repr(dosing)})


def closed_loop_record(policy: Any, seed: int, dither: float = 0.1, dither_hold_s: tuple[float, float] = (2.0, 20.0),
                       duration_s: float | None = None, dt: float = 0.5, env_kwargs: dict | None = None,
                       cycle: str = "random") -> Record:
    """Run ``policy`` (the policy protocol, e.g. an NMPC) on the random cycle of reset seed ``seed`` with a
    multiplicative dither on its dose, ``dose * (1 + e)``, ``e`` random steps in [-dither, dither] held
    ``dither_hold_s`` seconds, drawn from the seed independently of the measurements (the closed-loop
    identification's source of information that is uncorrelated with the noise, issue 18 trap 1); ``cycle``: the
    random-cycle family (:data:`scr_env.cycles.RANDOM_CYCLES`)."""
    from control.protocol import action_to_rate, rate_to_action
    from ident.excitation import RandomSteps
    from scr_env.envs.urea_scr import UreaSCREnv
    from scr_env.rollout import SIGNALS, Trajectory

    kw = dict(env_kwargs or {})
    kw["nh3_sensor"] = True
    if duration_s is not None:
        kw["random_cycle_duration_s"] = float(duration_s)
    env = UreaSCREnv(cycle=random_family(cycle), dt=dt, **kw)
    obs, info = env.reset(seed=seed)
    n = int(info["n_steps"])
    e = RandomSteps(-dither, dither, *dither_hold_s).generate(n, dt, np.random.SeedSequence([int(seed), 0xD17])) \
        if dither > 0 else np.zeros(n)
    if hasattr(policy, "attach"):
        policy.attach(env)
    rec = {k: np.empty(n) for k in SIGNALS}
    state = None
    from scr_env.physics import kernel as K

    b = env._batch
    drive = env._drive
    for k in range(n):
        a, state = policy.predict(obs, state, episode_start=np.array([k == 0]), deterministic=True)
        rate = action_to_rate(np.asarray(a).reshape(-1), env.max_rate_g_s) * (1.0 + e[k])
        obs, _, _, truncated, info = env.step(rate_to_action(min(max(rate, 0.0), env.max_rate_g_s), env.max_rate_g_s))
        out = b.out[0]
        rec["time_s"][k] = k * dt
        rec["adblue_g_s"][k] = info["adblue_g_s"]
        rec["exhaust_flow_mol_s"][k] = drive[k, 0]
        rec["inlet_temperature_k"][k] = drive[k, 1]
        rec["inlet_nox_ppm"][k] = drive[k, 2]
        rec["tailpipe_nox_ppm"][k] = out[K.O_NO] + out[K.O_NO2]
        rec["tailpipe_nh3_ppm"][k] = out[K.O_NH3]
        rec["nox_sensor_ppm"][k] = out[K.O_NOX_SENSOR]
        rec["nh3_sensor_ppm"][k] = out[K.O_NH3_SENSOR]
        if truncated:
            break
    tr = Trajectory(dt=dt, cycle=env.trace.name, signals=rec, observations=np.zeros((1, 1)),
                    observation_names=env.observation_names, kpis=info.get("episode_kpis", {}))
    return _record_from_trajectory(tr, {"kind": "closed_loop", "cycle": tr.cycle, "seed": int(seed),
                                        "dither": float(dither), "kpis": dict(tr.kpis)})


def training_arrays(records: Sequence[Record], features: FeatureMap, nox_kind: str = "ppm",
                    outputs: Sequence[str] = ("nox", "nh3")) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per record: (features (n, m), outputs (n, k)) with outputs among ``nox`` (in the ``nox_kind``
    representation), ``nh3`` (ppm) and ``sensor`` (NOx sensor ppm)."""
    us, ys = [], []
    for r in records:
        us.append(features.from_record(r.u))
        cols = []
        for o in outputs:
            if o == "nox":
                cols.append(nox_output(nox_kind, r.y[:, 0], r.u[:, 0]))
            elif o == "nh3":
                cols.append(r.y[:, 1])
            elif o == "sensor":
                cols.append(r.y[:, 2])
            else:
                raise ValueError(f"unknown output {o!r}")
        ys.append(np.column_stack(cols))
    return us, ys
