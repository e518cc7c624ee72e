"""An identified model as a Gymnasium environment: train an agent cheaply on the model, evaluate it on the plant.

Any model of :mod:`ident` exports ``to_casadi() -> casadi.Function('step', [x, u], [x_next, y])`` and works on
*normalised* signals (an :class:`ident.preprocessing.Normalizer` per side, fitted on the estimation data). A
:class:`SurrogateModel` bundles the model, both normalisers and the *physical* names of its inputs and outputs; the
environments here do the scaling explicitly at every step::

    u_phys = [signal(name) for name in input_names]          # from the drive cycle and the action
    x, y_norm = step(x, (u_phys - mean_u) / sd_u)            # the identified model
    y_phys = y_norm * sd_y + mean_y                          # back to ppm

Inputs may be any of :data:`INPUT_SIGNALS` (the drive cycle gives NOx, temperature, flow, NO2 share; the action
gives the dose, in g/s of AdBlue or, as in :mod:`ident.plant_data`, g/min of urea); outputs must include the tailpipe
NOx and NH3 (:data:`NOX_OUTPUTS`, :data:`NH3_OUTPUTS`), clipped to [0, inlet NOx] and [0, inf) since a linear model
can predict negative concentrations.

:class:`SurrogateSCREnv` (one plant) and :class:`SurrogateVectorEnv` (N plants, ``AutoresetMode.SAME_STEP``, one
batched model call per step, so :class:`control.rl.vec_env.GymVectorToSB3` trains on it) have the same spaces,
observation layout and reward as :class:`scr_env.envs.urea_scr.UreaSCREnv`:

* observation: upstream NOx [ppm], inlet temperature [K], exhaust flow [mol/s] (the cycle's values, no sensor lag or
  noise), tailpipe NOx sensor [ppm] = NO + 0.9 NO2 + NH3 of the model outputs (or the model's own sensor output if it
  has one), previous action;
* reward: ``-(w_nox * NOx [g as NO2] + w_nh3 * NH3 [g] + w_adblue * AdBlue [g])`` per step, weights as the env's
  ``reward_weights`` (the plant's own definition, :func:`scr_env.envs.kpis.account_step`);
* truncation at the end of the cycle with ``info["episode_kpis"]`` (:func:`scr_env.envs.kpis.episode_kpis`: tailpipe
  and engine-out NOx g and g/kWh, conversion, mean and peak slip, AdBlue g; no N2O or nitrogen balance);
* reset: the model state is settled for 120 s on the first cycle sample without dosing (an empty catalyst, as the
  plant's reset with zero coverage).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from scr_env.constants import UREA_G_MIN_PER_ADBLUE_G_S
from scr_env.cycles import ExhaustTrace, is_random_cycle
from scr_env.envs.config import make_config
from scr_env.envs.core import OBS_BASE, OBS_BASE_HIGH, OBS_BASE_LOW
from scr_env.envs.kpis import N_ACC, N_TERMS, account_batch, account_commands, episode_kpis
from scr_env.physics import kernel as K

__all__ = [
    "INPUT_SIGNALS",
    "SurrogateModel",
    "SurrogateSCREnv",
    "SurrogateVectorEnv",
    "fit_surrogate",
    "make_surrogate_training_env",
    "sim_to_real_gap",
]

#: input signals a surrogate may use, with their units
INPUT_SIGNALS = {"inlet_nox_ppm": "ppm", "inlet_temperature_k": "K", "exhaust_flow_mol_s": "mol/s",
                 "inlet_no2_fraction": "-", "adblue_g_s": "g/s", "urea_dosing_g_min": "g/min"}
NOX_OUTPUTS = ("tailpipe_nox_ppm",)
NH3_OUTPUTS = ("nh3_slip_ppm", "tailpipe_nh3_ppm")
SENSOR_OUTPUTS = ("nox_sensor_ppm",)
SETTLE_S = 120.0


@dataclass
class SurrogateModel:
    """An identified model with its signal scaling (see the module docstring).

    ``input_normalizer`` / ``output_normalizer``: objects with ``mean_`` and ``scale_`` (an
    :class:`ident.preprocessing.Normalizer`), or None if the model works on physical signals.
    """

    model: Any
    input_names: Sequence[str]
    output_names: Sequence[str]
    input_normalizer: Any = None
    output_normalizer: Any = None
    description: str = ""
    initial_state: Any = None  # callable: physical inputs (1, n_inputs) -> model state at reset; None: zeros

    def __post_init__(self) -> None:
        self.input_names = tuple(self.input_names)
        self.output_names = tuple(self.output_names)
        bad = [n for n in self.input_names if n not in INPUT_SIGNALS]
        if bad:
            raise ValueError(f"surrogate inputs {bad} unknown; inputs must be among {sorted(INPUT_SIGNALS)}")
        if not any(n in self.input_names for n in ("adblue_g_s", "urea_dosing_g_min")):
            raise ValueError("the surrogate needs a dosing input (adblue_g_s or urea_dosing_g_min)")
        if not any(n in self.output_names for n in NOX_OUTPUTS) or not any(n in self.output_names for n in NH3_OUTPUTS):
            raise ValueError(f"the surrogate needs a tailpipe NOx output {NOX_OUTPUTS} and an NH3 output "
                             f"{NH3_OUTPUTS} for the reward; got {self.output_names}")
        self._f = self.model.to_casadi()
        nx = self._f.size1_in(0)
        nu = self._f.size1_in(1)
        ny = self._f.size1_out(1)
        if nu != len(self.input_names) or ny != len(self.output_names):
            raise ValueError(f"the model has {nu} inputs and {ny} outputs, but {len(self.input_names)} input and "
                             f"{len(self.output_names)} output names were given")
        self.n_states = int(nx)

        def stats(norm: Any, n: int) -> tuple[np.ndarray, np.ndarray]:
            if norm is None:
                return np.zeros(n), np.ones(n)
            mean, scale = np.asarray(norm.mean_, dtype=float), np.asarray(norm.scale_, dtype=float)
            if mean.shape != (n,) or scale.shape != (n,):
                raise ValueError(f"normaliser statistics of shape {mean.shape} do not match {n} signals")
            return mean, scale

        self._u_mean, self._u_scale = stats(self.input_normalizer, nu)
        self._y_mean, self._y_scale = stats(self.output_normalizer, ny)
        self._mapped: dict[int, Any] = {}
        self._i_nox = next(self.output_names.index(n) for n in NOX_OUTPUTS if n in self.output_names)
        self._i_nh3 = next(self.output_names.index(n) for n in NH3_OUTPUTS if n in self.output_names)
        self._i_sensor = next((self.output_names.index(n) for n in SENSOR_OUTPUTS if n in self.output_names), None)

    def step(self, x: np.ndarray, u_phys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One step for a batch: ``x`` (B, n_states), ``u_phys`` (B, n_inputs) -> (x_next, y_phys (B, n_outputs))."""
        b = x.shape[0]
        f = self._mapped.get(b)
        if f is None:
            f = self._f if b == 1 else self._f.map(b)
            self._mapped[b] = f
        u = (u_phys - self._u_mean) / self._u_scale
        x_next, y = f(x.T, u.T)
        y_phys = np.asarray(y).reshape(-1, b).T * self._y_scale + self._y_mean
        return np.asarray(x_next).reshape(-1, b).T, y_phys

    def inputs(self, drive: np.ndarray, adblue_g_s: np.ndarray) -> np.ndarray:
        """Physical model inputs (B, n_inputs) from drive rows (B, 5: flow, T, NOx, NO2 share, power) and the dose."""
        cols = {"exhaust_flow_mol_s": drive[:, 0], "inlet_temperature_k": drive[:, 1], "inlet_nox_ppm": drive[:, 2],
                "inlet_no2_fraction": drive[:, 3], "adblue_g_s": adblue_g_s,
                "urea_dosing_g_min": adblue_g_s * UREA_G_MIN_PER_ADBLUE_G_S}
        return np.column_stack([cols[n] for n in self.input_names])

    def outputs(self, y: np.ndarray, drive: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(tailpipe NOx ppm, NH3 ppm, NOx sensor ppm), clipped to physical ranges."""
        nox = np.clip(y[:, self._i_nox], 0.0, np.maximum(drive[:, 2], 0.0))
        nh3 = np.maximum(y[:, self._i_nh3], 0.0)
        if self._i_sensor is not None:
            sensor = np.maximum(y[:, self._i_sensor], 0.0)
        else:
            sensor = nox * (1.0 - 0.1 * drive[:, 3]) + nh3
        return nox, nh3, sensor


def _drive(trace: ExhaustTrace) -> np.ndarray:
    return np.column_stack([trace.exhaust_flow_mol_s, trace.scr_inlet_temperature_k, trace.nox_ppm,
                            trace.no2_fraction, trace.engine_power_kw])


class _Batch:
    """State of B surrogate plants: model state, step index, cycle, episode accumulators."""

    def __init__(self, surrogate: SurrogateModel, n: int, dt: float, max_rate_g_s: float, weights: np.ndarray):
        self.s = surrogate
        self.n = n
        self.dt = dt
        self.max_rate = max_rate_g_s
        self.w = np.ascontiguousarray(np.broadcast_to(weights, (n, N_TERMS)), dtype=np.float64)
        self.x = np.zeros((n, surrogate.n_states))
        self.k = np.zeros(n, dtype=np.int64)
        self.end = np.zeros(n, dtype=np.int64)
        self.drives: list[np.ndarray] = [np.zeros((1, 5))] * n
        self.obs = np.zeros((n, len(OBS_BASE)), dtype=np.float32)
        # the plant step's input and output rows (scr_env.physics.kernel layouts), filled with what the model has,
        # so the reward and KPIs are the plant's (scr_env.envs.kpis)
        self.inputs = np.zeros((n, len(K.INPUT_FIELDS)))
        self.out = np.zeros((n, len(K.OUTPUT_FIELDS)))
        self.power = np.zeros(n)
        self.terms = np.zeros((n, N_TERMS))
        self.reward = np.zeros(n)
        self.acc = np.zeros((n, N_ACC))
        self.names = [""] * n

    def start(self, i: int, trace: ExhaustTrace, offset: int = 0) -> None:
        d = _drive(trace)
        self.drives[i] = d
        self.names[i] = trace.name
        self.k[i] = offset
        self.end[i] = d.shape[0]
        u0 = self.s.inputs(d[offset:offset + 1], np.zeros(1))
        if self.s.initial_state is None:
            x = np.zeros((1, self.s.n_states))
        else:
            x = np.asarray(self.s.initial_state(u0), dtype=float).reshape(1, self.s.n_states)
        for _ in range(int(SETTLE_S / self.dt)):
            x, y = self.s.step(x, u0)
        self.x[i] = x[0]
        self.acc[i] = 0.0
        _, _, sensor = self.s.outputs(y, d[offset:offset + 1])
        self.obs[i] = (d[offset, 2], d[offset, 1], d[offset, 0], sensor[0], -1.0)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a = np.clip(np.asarray(actions, dtype=np.float64).reshape(self.n), -1.0, 1.0)
        rate = 0.5 * (a + 1.0) * self.max_rate
        rows = np.stack([self.drives[i][self.k[i]] for i in range(self.n)])
        self.x, y = self.s.step(self.x, self.s.inputs(rows, rate))
        nox, nh3, sensor = self.s.outputs(y, rows)
        self.inputs[:, K.I_FLOW] = rows[:, 0]
        self.inputs[:, K.I_NOX] = rows[:, 2]
        self.inputs[:, K.I_ADBLUE] = rate
        self.out[:, K.O_NO] = nox  # the model's tailpipe NOx, counted as NO (the reward does not split NO/NO2)
        self.out[:, K.O_NH3] = nh3
        self.power[:] = rows[:, 4]
        account_commands(self.inputs[:, K.I_ADBLUE].copy(), self.acc)  # no actuator: command = delivered
        account_batch(self.inputs, self.power, self.dt, self.out, self.w, self.terms, self.reward, self.acc)
        reward = self.reward.copy()
        self.k += 1
        nxt = np.minimum(self.k, self.end - 1)
        nrows = np.stack([self.drives[i][nxt[i]] for i in range(self.n)])
        self.obs[:] = np.column_stack([nrows[:, 2], nrows[:, 1], nrows[:, 0], sensor, a])
        return reward, self.k >= self.end

    def kpis(self, i: int) -> dict[str, float]:
        return episode_kpis(self.acc[i])


def _spaces(max_rate: float) -> tuple[spaces.Box, spaces.Box]:
    obs = spaces.Box(np.array(OBS_BASE_LOW, dtype=np.float32), np.array(OBS_BASE_HIGH, dtype=np.float32),
                     dtype=np.float32)
    return obs, spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)


class SurrogateSCREnv(gym.Env):
    """One surrogate plant over a drive cycle (see the module docstring); ``cycle`` as for ``UreaSCREnv``.

    Arguments: ``surrogate`` (:class:`SurrogateModel`), ``cycle`` ("whtc", "whsc", "random", a CSV path or an
    ExhaustTrace), ``dt``, ``reward_weights`` (dict nox, nh3, adblue), ``cold_start``, ``random_cycle_duration_s``.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, surrogate: SurrogateModel, cycle: Any = "whtc", dt: float = 0.5,
                 reward_weights: dict | None = None, cold_start: bool = False,
                 random_cycle_duration_s: float = 1800.0) -> None:
        self.config = make_config(cycle=cycle, dt=dt, reward_weights=reward_weights, cold_start=cold_start,
                                  random_cycle_duration_s=random_cycle_duration_s)
        self.surrogate = surrogate
        self.dt = self.config.dt
        self.max_rate_g_s = self.config.dosing.max_rate_g_s
        self.observation_space, self.action_space = _spaces(self.max_rate_g_s)
        self.observation_names = tuple(OBS_BASE)
        self._b = _Batch(surrogate, 1, self.dt, self.max_rate_g_s, self.config.reward_weights.as_array())
        self._needs_reset = True

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        cfg = self.config
        if is_random_cycle(cfg.cycle):
            trace = cfg.trace(cfg.cycle, int(self.np_random.integers(0, 2**31 - 1)), cfg.cold_start)
        else:
            trace = cfg.trace(cfg.cycle, None, cfg.cold_start)
        self._b.start(0, trace)
        self._needs_reset = False
        return self._b.obs[0].copy(), {"cycle": trace.name, "n_steps": trace.n_steps, "dt": self.dt}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self._needs_reset:
            raise RuntimeError("call reset() before step()")
        a = np.asarray(action, dtype=np.float64)
        if a.size != 1 or not np.all(np.isfinite(a)):
            raise ValueError(f"action must be one finite number, got {action!r}")
        reward, done = self._b.step(a.reshape(1))
        info: dict[str, Any] = {}
        if done[0]:
            self._needs_reset = True
            info["episode_kpis"] = self._b.kpis(0)
        return self._b.obs[0].copy(), float(reward[0]), False, bool(done[0]), info

    def episode_kpis(self) -> dict[str, float]:
        """The KPIs of the current episode so far (as the plant's :meth:`UreaSCREnv.episode_kpis`)."""
        return self._b.kpis(0)


class SurrogateVectorEnv(VectorEnv):
    """``num_envs`` surrogate plants, one batched model call per step; ``AutoresetMode.SAME_STEP`` like
    :class:`scr_env.envs.vector.UreaSCRVectorEnv` (``infos["final_obs"]``, ``infos["final_info"]["episode_kpis"]``).
    With ``cycle="random"`` each reset draws from a pool of ``random_cycle_pool`` seeded random cycles; with
    ``random_offsets`` episodes start at a random step of the first half of the cycle."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": [], "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, surrogate: SurrogateModel, num_envs: int = 1, cycle: Any = "random", dt: float = 0.5,
                 reward_weights: dict | None = None, random_offsets: bool = False, random_cycle_pool: int = 32,
                 cold_start: bool = False) -> None:
        self.config = make_config(cycle=cycle, dt=dt, reward_weights=reward_weights, cold_start=cold_start)
        self.surrogate = surrogate
        self.num_envs = int(num_envs)
        self.dt = self.config.dt
        self.max_rate_g_s = self.config.dosing.max_rate_g_s
        self.single_observation_space, self.single_action_space = _spaces(self.max_rate_g_s)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_names = tuple(OBS_BASE)
        self.random_offsets = bool(random_offsets)
        self.random_cycle_pool = int(random_cycle_pool)
        self.render_mode = None
        self._b = _Batch(surrogate, self.num_envs, self.dt, self.max_rate_g_s, self.config.reward_weights.as_array())
        self._pool: list[ExhaustTrace] = []

    def _start(self, i: int) -> None:
        trace = self._pool[int(self.np_random.integers(len(self._pool)))]
        offset = int(self.np_random.integers(0, max(trace.n_steps // 2, 1))) if self.random_offsets else 0
        self._b.start(i, trace, offset)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        cfg = self.config
        if seed is not None or not self._pool:
            if is_random_cycle(cfg.cycle):
                seeds = self.np_random.integers(0, 2**31 - 1, size=self.random_cycle_pool)
                self._pool = [cfg.trace(cfg.cycle, int(s), cfg.cold_start) for s in seeds]
            else:
                self._pool = [cfg.trace(cfg.cycle, None, cfg.cold_start)]
        for i in range(self.num_envs):
            self._start(i)
        return self._b.obs.copy(), {}

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
        reward, done = self._b.step(actions)
        infos: dict[str, Any] = {}
        if done.any():
            final_obs = np.full(self.num_envs, None, dtype=object)
            final_info: dict[str, Any] = {}
            for i in np.flatnonzero(done):
                final_obs[i] = self._b.obs[i].copy()
                final_info = self._add_info(final_info, {"episode_kpis": self._b.kpis(int(i))}, int(i))
                self._start(int(i))
            infos.update(final_obs=final_obs, _final_obs=done.copy(), final_info=final_info, _final_info=done.copy())
        return self._b.obs.copy(), reward, np.zeros(self.num_envs, dtype=bool), done.copy(), infos


# --------------------------------------------------------------------------------------------- experiment helpers
def fit_surrogate(seeds: Sequence[int] = (101, 102, 103, 104), kind: str = "mm-arx",
                         na: int = 2, nb: int = 2) -> tuple[SurrogateModel, dict[str, Any]]:
    """Identify a surrogate on excitation data of random cycles (never the WHTC/WHSC held out for evaluation).

    Data: :func:`ident.plant_data.excitation_dataset` on the random cycles ``seeds`` (feedforward ANR 0.9 times
    ``1 + e``, e random steps in [-1, 1] held 4-60 s), concatenated, normalised with their own statistics;
    inputs (inlet NOx, urea g/min, inlet temperature, flow), outputs (tailpipe NOx, NH3 slip). ``kind``: "arx",
    "mm-arx" (local ARX models blended over 2 x 2 regions of temperature and flow, :mod:`ident.multiple_model`) or
    "greybox" (:class:`ident.greybox.StorageGreyBox`, physical signals, its own excitation at ANR 1).
    Returns the surrogate and a description with the one-step and simulation fit on a further random cycle.
    """
    from ident.dataset import IODataset
    from ident.excitation import RandomSteps
    from ident.linear import ARX
    from ident.metrics import compare
    from ident.multiple_model import MultipleModel, quantile_edges
    from ident.plant_data import excitation_dataset
    from ident.preprocessing import Normalizer
    from ident.stack import OutputStack

    exc = RandomSteps(low=-1.0, high=1.0, min_hold_s=4.0, max_hold_s=60.0)
    sets = [excitation_dataset("random", seed=s, base_anr=0.9, excitation=exc).select(outputs=[0, 1])
            for s in list(seeds) + [max(seeds) + 1]]
    est_sets, val = sets[:-1], sets[-1]
    u = np.concatenate([d.u for d in est_sets])
    y = np.concatenate([d.y for d in est_sets])
    nu = Normalizer(names=val.input_names).fit(u)
    ny = Normalizer(names=val.output_names).fit(y)
    un, yn = nu.transform(u), ny.transform(y)
    val_n = IODataset(u=nu.transform(val.u), y=ny.transform(val.y), dt=val.dt, input_names=val.input_names,
                      output_names=val.output_names)
    if kind == "greybox":
        # the control-oriented storage model of ident.greybox, fitted on its own excitation design (physical
        # signals, no normalisers): a model of the structure the linear ones lack
        from ident.greybox import StorageGreyBox

        exc_gb = RandomSteps(-0.9, 0.7, 10.0, 120.0)
        recs = [excitation_dataset("random", seed=s, base_anr=1.0, excitation=exc_gb) for s in seeds]
        vrec = excitation_dataset("random", seed=max(seeds) + 1, base_anr=1.0, excitation=exc_gb)
        gb = StorageGreyBox().fit([(r.u, r.y) for r in recs], None)
        yp = gb.predict(vrec.u)
        from ident.metrics import fit_percent

        fit = [float(fit_percent(vrec.y[:, j], yp[:, j])) for j in range(3)]
        desc = f"StorageGreyBox(n_cells={gb.n_cells}) on excitation data of random cycles {list(seeds)}"
        sur = SurrogateModel(gb, vrec.input_names, vrec.output_names, description=desc,
                             initial_state=lambda u0: gb.initial_state(u0))
        return sur, {"model": desc, "validation_fit_percent": fit, "validation_cycle_seed": int(max(seeds) + 1),
                     "inputs": list(vrec.input_names), "outputs": list(vrec.output_names)}
    if kind == "arx":
        model = ARX(na=na, nb=nb, nk=0).fit(un, yn)
        fit = np.atleast_1d(compare(model, val_n).fit).tolist()
    elif kind == "mm-arx":
        edges = [quantile_edges(un[:, c], 2) for c in (2, 3)]
        parts = [MultipleModel(scheduling=[2, 3], edges=edges, local="arx", na=na, nb=nb, nk=0).fit(un, yn[:, [j]])
                 for j in range(yn.shape[1])]
        model = OutputStack.from_models(parts)  # MISO local models side by side as one MIMO model
        fit = [float(np.atleast_1d(compare(m, val_n.select(outputs=[j])).fit)[0]) for j, m in enumerate(parts)]
    else:
        raise ValueError(f"kind must be 'arx' or 'mm-arx', got {kind!r}")
    desc = f"{type(model).__name__}({kind}, na={na}, nb={nb}, nk=0) on excitation data of random cycles {list(seeds)}"
    sur = SurrogateModel(model, val.input_names, val.output_names, nu, ny, description=desc)
    info = {"model": desc, "validation_fit_percent": fit,
            "validation_cycle_seed": int(max(seeds) + 1), "inputs": list(val.input_names),
            "outputs": list(val.output_names)}
    return sur, info


def make_surrogate_training_env(num_envs: int, seed: int, pipeline: Any, env_kwargs: dict | None = None,
                                kind: str = "mm-arx") -> tuple[Any, dict[str, Any]]:
    """Fit a surrogate (:func:`fit_surrogate`) and wrap a :class:`SurrogateVectorEnv` on random cycles for
    SB3 (adapter, VecMonitor, observation pipeline); returns (venv, info incl. the surrogate object)."""
    from stable_baselines3.common.vec_env import VecMonitor

    from control.rl.pipeline import PipelineVecEnv
    from control.rl.vec_env import GymVectorToSB3

    sur, info = fit_surrogate(kind=kind)
    kw = {k: v for k, v in (env_kwargs or {}).items() if k in ("reward_weights", "dt")}
    venv = SurrogateVectorEnv(sur, num_envs=num_envs, cycle="random", random_offsets=True, **kw)
    sb3 = GymVectorToSB3(venv)
    sb3.seed(seed)
    wrapped = PipelineVecEnv(VecMonitor(sb3), pipeline)
    wrapped.observation_names = tuple(OBS_BASE)
    info.update(observation_names=list(OBS_BASE), env_kwargs={"cycle": "random", "surrogate": True, **kw},
                surrogate_object=sur, reward_weights=kw.get("reward_weights"))
    return wrapped, info


def sim_to_real_gap(policy: Any, surrogate_info: dict[str, Any], cycles: Sequence[str] = ("whtc", "whsc"),
                    seeds: Sequence[int] = (0,)) -> dict[str, Any]:
    """KPIs of ``policy`` on the surrogate and on the first-principles plant for each cycle (mean over seeds)."""
    from control.evaluation import evaluate, summarise

    sur = surrogate_info["surrogate_object"]
    out: dict[str, Any] = {}
    for cycle in cycles:
        rows = [r.kpis for r in evaluate(policy, env=SurrogateSCREnv(sur, cycle=cycle), seeds=seeds, name="rl")]
        sim = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
        real = summarise(evaluate(policy, cycles=(cycle,), seeds=seeds, name="rl"))[cycle]["rl"]
        out[cycle] = {"surrogate": sim, "plant": {k: real[k] for k in sim if k in real},
                      "gap_tailpipe_nox_g_per_kwh": real["tailpipe_nox_g_per_kwh"] - sim["tailpipe_nox_g_per_kwh"],
                      "gap_mean_nh3_slip_ppm": real["mean_nh3_slip_ppm"] - sim["mean_nh3_slip_ppm"]}
    return out
