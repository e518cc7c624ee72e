"""The urea-dosing SCR environment (one catalyst)."""
from __future__ import annotations

import math
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from scr_env.cycles import ExhaustTrace, is_random_cycle
from scr_env.envs import core
from scr_env.envs.config import O2_FRACTION, EnvConfig, flag, make_config, reset_coverage, reset_options
from scr_env.params import pack
from scr_env.physics import kernel as K

RESET_OPTIONS = ("cold_start", "initial_coverage", "cycle_seed")
#: the longest ``disturbance_preview`` accepted, in steps, when the episode is shorter [chosen: 32 MB of float64; rows
#: past the end of the cycle only repeat its last row]
MAX_PREVIEW_STEPS = 1_000_000
_F32 = np.dtype(np.float32)
_F64 = np.dtype(np.float64)


class UreaSCREnv(gym.Env):
    r"""AdBlue dosing of a Cu-zeolite SCR catalyst on a heavy-duty diesel over a drive cycle.

    ## Description
    A 12-13 L Euro VI diesel runs a drive cycle (WHTC, WHSC, a seeded random cycle or measured data); an engine-out
    model and the thermal inertia of DOC and DPF give the exhaust at the SCR inlet (flow, temperature, NOx and its NO2
    share). The agent sets the AdBlue (AUS 32) injection rate upstream of the catalyst every ``dt`` seconds. The
    catalyst is a first-principles multi-cell model (NH3 storage with Temkin desorption; standard, fast and NO2 SCR;
    NH3 oxidation to N2, NO and N2O; solid temperature per cell) calibrated to CLEERS Cu-SSZ-13 lab data
    (``scr_env/data/catalyst``). The tailpipe NOx sensor is cross-sensitive to NH3, so the controller cannot tell NOx
    from NH3 slip by that sensor alone.

    ## Action Space
    ``Box(-1, 1, (1,), float32)`` by default (``action_mode="normalized"``):

    | action | meaning | physical value |
    |---|---|---|
    | a in [-1, 1] | AdBlue injection rate | (a + 1) / 2 * ``dosing.max_rate_g_s`` [g/s] (3.0 g/s default) |

    With ``action_mode="physical"`` the space is ``Box(0, max_rate_g_s, (1,))`` in g/s. Out-of-range actions are
    clipped to the bounds (the clipped value is what is commanded and observed). With ``actuator`` (see
    :mod:`scr_env.actuator`) the injector delivers the command through a first-order lag and a slew limit: the plant,
    the reward, the KPIs and ``info["adblue_g_s"]`` see the delivered rate, the observation's previous action stays
    the command. An action must be a real
    number: a float or int scalar or array of one element. NaN, inf, a wrong shape or anything else (None, a string,
    a bool, a complex number) raises ``ValueError``.

    ## Observation Space
    ``Box(float32)``; what a truck measures, with lags and noise (see :class:`scr_env.params.SensorParams`):

    | index | name | unit | range |
    |---|---|---|---|
    | 0 | upstream (engine-out) NOx sensor | ppm | 0 to 10000 |
    | 1 | SCR inlet temperature (thermocouple, 3 s lag) | K | 0 to 1500 |
    | 2 | exhaust flow (ECU estimate, 2 % noise) | mol/s | 0 to 100 |
    | 3 | tailpipe NOx sensor: NO + 0.9 NO2 + 1.0 NH3, 1 s lag | ppm | 0 to 10000 |
    | 4 | previous action (normalised) | - | -1 to 1 |
    | 5 | tailpipe NH3 sensor (only with ``nh3_sensor=True``) | ppm | 0 to 10000 |
    | next N | NH3 coverage of each cell (only with ``privileged=True``; never measurable) | - | 0 to 1 |

    A reading outside its range is clipped to it in the observation (a sensor saturates); the physics, rewards and
    ``info`` use the real value. The shipped cycles stay well inside (WHTC, WHSC and random cycles of the default
    engine: flow up to about 18 mol/s, inlet temperature up to about 780 K, NOx up to about 2300 ppm); a measured
    cycle (CSV, ExhaustTrace) or a larger engine above 100 mol/s is simulated at its real flow but observed at
    100 mol/s.

    ## Rewards
    An economic cost in grams of AdBlue equivalent (weights ``reward_weights``, see
    :class:`scr_env.envs.kpis.RewardWeights`): per step
    ``r = -(20 * tailpipe NOx [g as NO2] + 60 * NH3 slip [g] + 1 * AdBlue [g])``. Each term is in ``info``
    (``nox_cost``, ``nh3_cost``, ``adblue_cost``, all <= 0).

    ## Starting State
    Hot start by default: the cells at the SCR inlet temperature of the first sample, NH3 coverage
    ``initial_coverage`` (0 by default); ``cold_start=True`` starts the aftertreatment at 298.15 K (cold WHTC).
    ``reset(options=...)`` takes None or a dict with the keys ``cold_start`` (True or False),
    ``initial_coverage`` (a number in [0, 1]) and, for a random cycle only, ``cycle_seed`` (a non-negative int;
    None: drawn from ``self.np_random``). Any other key or value raises ``ValueError`` naming it, before the
    reset changes anything (``cycle_seed`` on a fixed cycle included: it would be ignored). Sensor noise and the
    random cycle come from ``self.np_random``.

    ## Episode End
    Truncation at the end of the drive cycle (3600 steps for the WHTC at 0.5 s). The episode never terminates.
    At the truncating step ``info["episode_kpis"]`` holds ``nox_conversion``, ``engine_out_nox_g_per_kwh``,
    ``tailpipe_nox_g_per_kwh``, ``mean_nh3_slip_ppm``, ``peak_nh3_slip_ppm``, ``adblue_g``, ``engine_work_kwh`` and
    more (see :func:`scr_env.envs.kpis.episode_kpis`). Stepping after truncation without ``reset`` raises. An episode
    ended early by a wrapper (``gym.make(..., max_episode_steps=N)`` adds ``TimeLimit``) has its KPIs from
    :meth:`episode_kpis` (``env.unwrapped.episode_kpis()``), or in ``info`` with the outermost wrapper
    :class:`scr_env.wrappers.RecordEpisodeKPIs`.

    ## Arguments
    ``gymnasium.make("scr_env/UreaSCR-v0", **kwargs)`` with:

    | argument | default | meaning |
    |---|---|---|
    | cycle | "whtc" | "whtc", "whsc", "random" / "random_modes" (seeded WHTC- / WHSC-like per reset), CSV, trace |
    | catalyst | "cu_zeolite" | preset name or :class:`~scr_env.params.CatalystParams` |
    | dt | 0.5 | control interval [s] (the thesis data: 0.5 s) |
    | age_h | 0.0 | catalyst hydrothermal ageing [h], 0-16 (the CLEERS samples), or (lo, hi) drawn per reset |
    | ageing | 0.0 | older form: ageing severity in [0, 1] = age_h / 16 (:func:`scr_env.params.aged`) |
    | sensor_noise | True | False removes sensor noise (lags stay) |
    | sensors, dosing | defaults | :class:`~scr_env.params.SensorParams`, :class:`~scr_env.params.DosingParams` |
    | reward_weights | None | dict with keys nox, nh3, adblue |
    | action_mode | "normalized" | or "physical" (g/s) |
    | nh3_sensor | False | add a tailpipe NH3 sensor to the observation |
    | privileged | False | add the cell coverages to the observation (oracles, debugging) |
    | cold_start | False | aftertreatment starts at ambient temperature |
    | randomize | 0.0 | domain randomisation spread (e.g. 0.2 = +/-20 %) of capacity, activity and volume per reset |
    | initial_coverage | 0.0 | NH3 coverage at reset |
    | actuator | None | dosing unit (lag, slew limit): None, "default", a dict or ``scr_env.actuator.ActuatorParams`` |
    | render_mode | None | "rgb_array" or "human": plot of the episode so far |

    Flags (``sensor_noise``, ``nh3_sensor``, ``privileged``, ``cold_start``) must be ``True``/``False`` (or numpy
    bools) and numbers must be numbers: ``nh3_sensor="no"`` or ``dt="0.5"`` raise ``ValueError`` naming the argument.

    ## Version History
    * v0: initial version.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["human", "rgb_array"], "render_fps": 4}

    def __init__(self, render_mode: str | None = None, **kwargs: Any) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        self.render_mode = render_mode
        self.config: EnvConfig = make_config(**kwargs)
        cfg = self.config
        self.dt = cfg.dt
        self.max_rate_g_s = cfg.dosing.max_rate_g_s
        if cfg.action_mode == "normalized":
            self.action_space = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
        else:
            self.action_space = spaces.Box(0.0, np.float32(self.max_rate_g_s), shape=(1,), dtype=np.float32)
        low, high = cfg.obs_bounds()
        self.observation_space = spaces.Box(low, high, dtype=np.float32)
        self.observation_names = cfg.obs_names
        self._batch = core.PlantBatch(1, cfg.catalyst.n_cells, low.size, cfg.nh3_sensor, cfg.privileged)
        self._batch.aux_params[0] = K.pack_aux(cfg.dosing, cfg.sensors)
        self._batch.weights[0] = cfg.reward_weights.as_array()
        self._batch.set_actuator(cfg.actuator, cfg.dt)
        self._base_params = pack(cfg.effective_catalyst)
        self._fixed_trace: ExhaustTrace | None = None
        if not is_random_cycle(cfg.cycle):
            self._fixed_trace = cfg.trace(cfg.cycle, None, cfg.cold_start)
        self.trace: ExhaustTrace | None = None
        self._drive = np.zeros((0, 6))
        self._noise = np.zeros((0, K.N_NOISE))
        self._k = 0
        self._n = 0
        self._row = np.zeros(1, dtype=np.int64)
        self._nox_list: list[float] = []
        self._needs_reset = True
        self._history: list[tuple[float, ...]] = []
        self._fig = None

    # ------------------------------------------------------------------------------------------------- reset/step
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        cfg = self.config
        # every option is checked before anything changes (a failed reset leaves the generator and episode as they were)
        options = reset_options(options, RESET_OPTIONS)
        cold = flag("options['cold_start']", options["cold_start"]) if "cold_start" in options else cfg.cold_start
        coverage = reset_coverage(options, cfg.initial_coverage)
        cycle_seed = options.get("cycle_seed")
        if cycle_seed is not None:
            if not is_random_cycle(cfg.cycle):
                raise ValueError(f"options['cycle_seed'] applies to a random cycle ('random', 'random_modes') only; "
                                 f"this environment replays the fixed cycle {self._fixed_trace.name!r} "
                                 f"(got cycle_seed={cycle_seed!r})")
            if isinstance(cycle_seed, (bool, np.bool_)) or not isinstance(cycle_seed, (int, np.integer)) \
                    or cycle_seed < 0:
                raise ValueError(f"options['cycle_seed'] must be a non-negative integer (the seed of the random "
                                 f"cycle), got {cycle_seed!r}")
        super().reset(seed=seed)
        if is_random_cycle(cfg.cycle):
            if cycle_seed is None:
                cycle_seed = int(self.np_random.integers(0, 2**31 - 1))
            self.trace = cfg.trace(cfg.cycle, int(cycle_seed), cold)
        elif cold != cfg.cold_start:
            self.trace = cfg.trace(cfg.cycle, None, cold)
        else:
            self.trace = self._fixed_trace
        tr = self.trace
        self._drive = core.drive_table(tr, O2_FRACTION)
        self._nox_list = tr.nox_ppm.tolist()
        self._n = tr.n_steps
        self._noise = self.np_random.standard_normal((self._n, K.N_NOISE))
        b = self._batch
        b.start_episode(0, cfg, self.np_random, self._base_params, self._drive[0], cold, coverage)
        self._k = 0
        self._needs_reset = False
        self._history = []
        if self.render_mode is not None:
            nox0 = float(tr.nox_ppm[0])
            self._record(0.0, nox0, nox0, 0.0, 0.0, float(tr.scr_inlet_temperature_k[0]), coverage)
        return b.obs[0].copy(), {"cycle": tr.name, "n_steps": self._n, "dt": self.dt}

    def _to_norm(self, rate_g_s: float) -> float:
        return 2.0 * rate_g_s / self.max_rate_g_s - 1.0

    def _dose(self, action: Any) -> tuple[float, float]:
        """(AdBlue rate g/s, normalised action) from an action after validation and clipping."""
        if type(action) is np.ndarray and action.shape == (1,) and (action.dtype is _F32 or action.dtype is _F64):
            v = float(action[0])  # the fast path: what agents pass
        else:
            v = self._action_value(action)
        if not math.isfinite(v):
            raise ValueError(f"action must be finite, got {v!r}")
        if self.config.action_mode == "normalized":
            a = min(max(v, -1.0), 1.0)
            return 0.5 * (a + 1.0) * self.max_rate_g_s, a
        rate = min(max(v, 0.0), self.max_rate_g_s)
        return rate, self._to_norm(rate)

    @staticmethod
    def _action_value(action: Any) -> float:
        """The value of an action that is not a float32/float64 array of shape (1,): a real number (float or int
        scalar or array of one element), else ValueError."""
        expected = "action must be a real number or an array of shape (1,) (float or int)"
        if action is None:
            raise ValueError(f"{expected}, got None")
        try:
            arr = np.asarray(action)
        except (TypeError, ValueError):
            raise ValueError(f"{expected}, got {action!r}") from None
        if arr.dtype.kind not in "fiu":
            what = {"c": "complex", "b": "bool", "U": "string", "S": "bytes", "O": "object"}.get(arr.dtype.kind,
                                                                                                 str(arr.dtype))
            raise ValueError(f"{expected}, got a {what} value {action!r}")
        if arr.size != 1 or arr.ndim > 1:
            raise ValueError(f"action must have shape (1,), got shape {arr.shape}")
        return float(arr.reshape(-1)[0])

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self._needs_reset:
            raise RuntimeError("the episode has ended (or never started): call reset() before step()")
        rate, a_norm = self._dose(action)
        b = self._batch
        k = self._k
        buf = b.buf
        buf[0, b.col_adblue] = rate
        buf[0, b.col_action] = a_norm
        self._row[0] = k
        b.step(self.dt, self._drive, self._row, self._noise, self._row)
        self._k = k + 1
        truncated = self._k >= self._n
        out = b.out[0].tolist()
        terms = b.terms[0].tolist()
        info = {
            "nox_cost": terms[0], "nh3_cost": terms[1], "adblue_cost": terms[2],
            "tailpipe_nox_ppm": out[K.O_NO] + out[K.O_NO2], "tailpipe_nh3_ppm": out[K.O_NH3],
            "engine_out_nox_ppm": self._nox_list[k], "adblue_g_s": float(buf[0, b.col_adblue]),
            "time_s": self._k * self.dt,
        }
        if self.render_mode is not None:
            self._record(self._k * self.dt, info["engine_out_nox_ppm"], info["tailpipe_nox_ppm"],
                         info["tailpipe_nh3_ppm"], info["adblue_g_s"], float(self._drive[k, 1]), out[K.O_COV])
        if truncated:
            self._needs_reset = True
            info["episode_kpis"] = core.episode_kpis(b.acc[0], out[K.O_STORED])
        return b.obs[0].copy(), buf[0, b.col_reward], False, truncated, info

    def episode_kpis(self) -> dict[str, float]:
        """The KPIs of the current (or just ended) episode so far: what ``info["episode_kpis"]`` holds at the end
        of the cycle, available after any step, e.g. when ``TimeLimit`` (``gym.make(..., max_episode_steps=N)``) or
        the caller ends the episode early (see also :class:`scr_env.wrappers.RecordEpisodeKPIs`). RuntimeError
        before the first ``reset``."""
        if self.trace is None:
            raise RuntimeError("episode_kpis() needs an episode: call reset() first")
        b = self._batch
        # NH3 stored now: the plant step's figure, or before the first step the initial one
        stored = float(b.out[0, K.O_STORED]) if self._k > 0 else float(b.acc[0, core.A_STORED0_MOL])
        return core.episode_kpis(b.acc[0], stored)

    # ------------------------------------------------------------------------------------------- introspection
    @property
    def state(self) -> dict[str, np.ndarray]:
        """Privileged plant state (copies): cell coverages [-] and solid temperatures [K], sensor lag states."""
        b = self._batch
        return {"nh3_coverage": b.theta[0].copy(), "temperature_k": b.temperature_k[0].copy(),
                "sensor_state": b.sensor_state[0].copy()}

    @property
    def step_index(self) -> int:
        """Number of steps taken in this episode."""
        return self._k

    @property
    def catalyst_params_array(self) -> np.ndarray:
        """Packed parameters of the catalyst of this episode (after ageing and randomisation)."""
        return self._batch.cat_params[0].copy()

    def disturbance_preview(self, horizon: int) -> np.ndarray:
        """The next ``horizon`` rows of (flow mol/s, inlet temperature K, NOx ppm, NO2 fraction) of the cycle, the
        last row repeated past its end: the cycle preview an MPC may be given (privileged information).

        ``horizon`` is a number of steps: an integer in [0, max(episode length, ``MAX_PREVIEW_STEPS`` = 10**6)]
        (ValueError otherwise); 0 gives an empty (0, 4) array. RuntimeError before the first ``reset``."""
        if self.trace is None:
            raise RuntimeError("disturbance_preview() needs an episode: call reset() first")
        if isinstance(horizon, (bool, np.bool_)) or not isinstance(horizon, (int, np.integer)):
            raise ValueError(f"horizon must be a non-negative integer number of steps, got {horizon!r}")  # noqa: TRY004
        h = int(horizon)
        cap = max(self._n, MAX_PREVIEW_STEPS)
        if not 0 <= h <= cap:
            raise ValueError(f"horizon must be in [0, {cap}] steps (rows past the end of the cycle only repeat its "
                             f"last row), got {horizon!r}")
        idx = np.minimum(np.arange(self._k, self._k + h), max(self._n - 1, 0))
        return self._drive[idx, :4].copy()

    # --------------------------------------------------------------------------------------------------- render
    def _record(self, t: float, nox_in: float, nox_out: float, nh3_out: float, rate: float, t_in: float,
                cov: float) -> None:
        self._history.append((t, nox_in, nox_out, nh3_out, rate, t_in, cov))

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array' or 'human'")
            return None
        import matplotlib.pyplot as plt

        from scr_env.envs.rendering import episode_figure, figure_to_rgb

        if self.render_mode == "rgb_array":
            fig = episode_figure(np.asarray(self._history))
            image = figure_to_rgb(fig)
            plt.close(fig)
            return image
        fig = episode_figure(np.asarray(self._history), self._fig)

        self._fig = fig
        plt.pause(0.001)
        return None

    def close(self) -> None:
        if self._fig is not None:
            import matplotlib.pyplot as plt

            plt.close(self._fig)
            self._fig = None
