"""The native vector environment: N catalysts stepped by one call of the compiled physics."""
from __future__ import annotations

import sys
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from scr_env.cycles import MAX_TRACE_SAMPLES, ExhaustTrace, is_random_cycle
from scr_env.envs import core
from scr_env.envs.config import O2_FRACTION, flag, make_config, reset_coverage, reset_options
from scr_env.params import pack
from scr_env.physics import kernel as K

RESET_OPTIONS = ("initial_coverage", "reset_mask")
AUTORESET_MODES = (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP)
#: the adapter that makes this environment a stable-baselines3 VecEnv (the error for a raw one names it)
SB3_ADAPTER_HINT = ("wrap it with control.rl.vec_env.GymVectorToSB3(venv) -- the environment made with "
                    "autoreset_mode='same_step' -- or make it with control.rl.vec_env.make_sb3_vec_env(num_envs, "
                    "...), which does both")


def _autoreset_mode(value: Any) -> AutoresetMode:
    """``value`` (an AutoresetMode or its name/value, any case) as one of :data:`AUTORESET_MODES`."""
    if isinstance(value, AutoresetMode):
        mode = value
    elif isinstance(value, str):
        key = value.strip().lower().replace("-", "_")
        mode = next((m for m in AutoresetMode if key in (m.value.lower(), m.name.lower())), None)
    else:
        mode = None
    if mode not in AUTORESET_MODES:
        raise ValueError(f"autoreset_mode must be AutoresetMode.NEXT_STEP ('next_step', Gymnasium's default) or "
                         f"AutoresetMode.SAME_STEP ('same_step'), got {value!r}")
    return mode


def _guard_against_raw_use_in_sb3() -> None:
    """If stable-baselines3 is imported, make its ``isinstance(env, VecEnv)`` check (the first thing it does with an
    environment) raise a TypeError naming the adapter when given a Gymnasium vector environment: SB3 would
    otherwise wrap it as a single environment and fail with a message about OpenAI Gym. Installed once, by a class
    that only answers that check (``abc`` consults the ``__subclasshook__`` of every subclass of ``VecEnv``)."""
    module = sys.modules.get("stable_baselines3.common.vec_env")
    if module is None or getattr(module, "_scr_env_guard", False):
        return
    from gymnasium.vector import VectorEnv as GymVectorEnv

    class _GymnasiumVectorEnvGuard(module.VecEnv):  # never instantiated
        @classmethod
        def __subclasshook__(cls, subclass: type) -> Any:
            if cls is _GymnasiumVectorEnvGuard and isinstance(subclass, type) and issubclass(subclass, GymVectorEnv):
                raise TypeError(f"{subclass.__name__} is a Gymnasium vector environment, which stable-baselines3 "
                                f"cannot use as it is: {SB3_ADAPTER_HINT}")
            return NotImplemented

    module._scr_env_guard = _GymnasiumVectorEnvGuard


class UreaSCRVectorEnv(VectorEnv):
    """``num_envs`` independent SCR plants (see :class:`scr_env.envs.urea_scr.UreaSCREnv` for the spec of one).

    Every step advances all plants with one compiled call of the same per-plant code the single environment uses (on
    all threads for large batches, unless a busy machine makes the serial loop faster). Create it with
    ``gymnasium.make_vec("scr_env/UreaSCR-v0", num_envs=N, vectorization_mode="vector_entry_point", **kwargs)``.

    Beyond the single environment's arguments:

    | argument | default | meaning |
    |---|---|---|
    | num_envs | 1 | number of plants |
    | cycle | "whtc" | one cycle for all plants, or a sequence of ``num_envs`` cycles (names, paths, ExhaustTraces) |
    | random_offsets | False | start each episode at a random step of its cycle, so plants are not in lockstep |
    | random_cycle_pool | 32 | with a random cycle: size of the pool of seeded random cycles drawn from at each reset |
    | autoreset_mode | "next_step" | Gymnasium's ``AutoresetMode.NEXT_STEP`` or ``SAME_STEP`` (or their names) |
    | max_episode_steps | None | truncate every episode after this many steps (if the cycle has not ended before) |

    ``reset(options=...)`` takes None or a dict with the keys ``initial_coverage`` (a number in [0, 1], for the
    plants reset) and ``reset_mask``: Gymnasium's boolean array of shape ``(num_envs,)``, True for the plants to
    reset (the others keep running); integer indices, other dtypes or shapes raise ``ValueError``, and so does a
    partial mask on the first reset or together with a seed (the cycles of all plants are rebuilt from the seed).
    Any other key raises ``ValueError``, before the reset changes anything.

    Actions: a float or int array of shape ``(num_envs, 1)`` or ``(num_envs,)``, clipped to the action space; NaN,
    inf, another shape or a non-real dtype (bool, complex, object, string) raise ``ValueError``.

    Autoreset (``metadata["autoreset_mode"]``, set by ``autoreset_mode``; Gymnasium's vector wrappers such as
    ``NormalizeObservation`` need ``NEXT_STEP``, stable-baselines3's adapter
    :class:`control.rl.vec_env.GymVectorToSB3` needs ``SAME_STEP``):

    * ``NEXT_STEP`` (default): the step that ends a plant's episode returns its last observation, ``truncated[i]``
      and ``infos["episode_kpis"]`` (masked by ``infos["_episode_kpis"]``); the next step ignores that plant's
      action and returns its reset observation with reward 0 (``infos["cycle"]`` names its new cycle).
    * ``SAME_STEP``: the step that ends an episode returns the reset observation at once, with
      ``infos["final_obs"][i]`` and ``infos["final_info"]`` (holding ``episode_kpis``) for the ended plants.

    Per-step ``infos`` hold arrays ``nox_cost``, ``nh3_cost``, ``adblue_cost``, ``tailpipe_nox_ppm``,
    ``tailpipe_nh3_ppm``, ``adblue_g_s`` and ``step_index`` (masked out for a plant on its NEXT_STEP reset step).
    :meth:`episode_kpis` gives the KPIs of every plant's episode so far at any time. Passing this environment to
    stable-baselines3 as it is raises a ``TypeError`` that names the adapter.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, cycle: Any = "whtc", random_offsets: bool = False,
                 random_cycle_pool: int = 32, render_mode: str | None = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP, max_episode_steps: int | None = None,
                 **kwargs: Any) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.autoreset_mode = _autoreset_mode(autoreset_mode)
        self.metadata = {**type(self).metadata, "autoreset_mode": self.autoreset_mode}
        if max_episode_steps is not None and (isinstance(max_episode_steps, bool) or not isinstance(
                max_episode_steps, (int, np.integer)) or max_episode_steps < 1):
            raise ValueError(f"max_episode_steps must be None or a positive integer, got {max_episode_steps!r}")
        self.max_episode_steps = None if max_episode_steps is None else int(max_episode_steps)
        if render_mode is not None:
            raise ValueError("the vector environment does not render; use the single environment for plots")
        if isinstance(random_cycle_pool, bool) or not isinstance(random_cycle_pool, (int, np.integer)) \
                or random_cycle_pool < 1:
            raise ValueError(f"random_cycle_pool must be a positive integer, got {random_cycle_pool!r}")
        self.num_envs = int(num_envs)
        if isinstance(cycle, (list, tuple)):
            if len(cycle) != self.num_envs:
                raise ValueError(f"cycle: a sequence of cycles must have num_envs = {self.num_envs} entries, "
                                 f"got {len(cycle)}")
            cycles = list(cycle)
        else:
            cycles = [cycle] * self.num_envs
        self._configs = {}
        for c in cycles:
            key = self._key(c)
            if key not in self._configs:
                self._configs[key] = make_config(cycle=c, **kwargs)
        self._cycle_keys = [self._key(c) for c in cycles]
        cfg = self._configs[self._cycle_keys[0]]
        if any(is_random_cycle(c.cycle) for c in self._configs.values()):
            # the pool of random cycles shares one drive table: bounded as one trace is (scr_env.cycles)
            rows = int(random_cycle_pool) * (cfg.random_cycle_duration_s / cfg.dt)
            if not rows <= MAX_TRACE_SAMPLES:
                raise ValueError(f"random_cycle_pool = {random_cycle_pool} random cycles of "
                                 f"{cfg.random_cycle_duration_s:g} s at dt = {cfg.dt:g} s would hold {rows:,.0f} "
                                 f"samples, more than MAX_TRACE_SAMPLES = {MAX_TRACE_SAMPLES:,}; use a smaller pool, "
                                 f"shorter cycles or a larger dt")
        self.config = cfg
        self.dt = cfg.dt
        self.max_rate_g_s = cfg.dosing.max_rate_g_s
        self.random_offsets = flag("random_offsets", random_offsets)
        self._normalized_actions = cfg.action_mode == "normalized"
        self.random_cycle_pool = int(random_cycle_pool)
        self.render_mode = None
        if cfg.action_mode == "normalized":
            self.single_action_space = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
        else:
            self.single_action_space = spaces.Box(0.0, np.float32(self.max_rate_g_s), shape=(1,), dtype=np.float32)
        low, high = cfg.obs_bounds()
        self.single_observation_space = spaces.Box(low, high, dtype=np.float32)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.observation_names = cfg.obs_names
        n = self.num_envs
        self._batch = core.PlantBatch(n, cfg.catalyst.n_cells, low.size, cfg.nh3_sensor, cfg.privileged)
        self._batch.aux_params[:] = K.pack_aux(cfg.dosing, cfg.sensors)
        self._batch.weights[:] = cfg.reward_weights.as_array()
        self._batch.set_actuator(cfg.actuator, cfg.dt)
        self._base_params = pack(cfg.effective_catalyst)
        self._traces: list[ExhaustTrace] = []
        self._flat = np.zeros((0, 6))
        self._trace_base = np.zeros(0, dtype=np.int64)
        self._trace_len = np.zeros(0, dtype=np.int64)
        self._fixed_index: dict[str, int] = {}
        self._pool_index: dict[str, list[int]] = {}  # per random-cycle name, the pool's trace indices
        self._env_trace = np.zeros(n, dtype=np.int64)
        self._base = np.zeros(n, dtype=np.int64)
        self._len = np.zeros(n, dtype=np.int64)
        self._k = np.zeros(n, dtype=np.int64)
        self._ones = np.ones(n, dtype=bool)
        self._row = np.zeros(n, dtype=np.int64)
        self._noise = np.zeros((n, K.N_NOISE))
        self._autoreset = np.zeros(n, dtype=bool)  # NEXT_STEP: plants to reset at the next step
        self._no_skip = np.zeros(n, dtype=bool)
        self._needs_reset = True
        self._rng_ready = False
        _guard_against_raw_use_in_sb3()

    @staticmethod
    def _key(cycle: Any) -> str:
        return f"trace:{id(cycle)}" if isinstance(cycle, ExhaustTrace) else f"name:{cycle}"

    # ----------------------------------------------------------------------------------------------- cycles
    def _build_traces(self, seed_rng: np.random.Generator) -> None:
        traces: list[ExhaustTrace] = []
        self._fixed_index = {}
        self._pool_index = {}
        for key, cfg in self._configs.items():
            if is_random_cycle(cfg.cycle):
                if cfg.cycle not in self._pool_index:
                    pool = self._pool_index[cfg.cycle] = []
                    seeds = seed_rng.integers(0, 2**31 - 1, size=self.random_cycle_pool)
                    for s in seeds:
                        pool.append(len(traces))
                        traces.append(cfg.trace(cfg.cycle, int(s), cfg.cold_start))
            else:
                self._fixed_index[key] = len(traces)
                traces.append(cfg.trace(cfg.cycle, None, cfg.cold_start))
        self._traces = traces
        tables = [core.drive_table(t, O2_FRACTION) for t in traces]
        self._trace_len = np.array([t.shape[0] for t in tables], dtype=np.int64)
        self._trace_base = np.concatenate([[0], np.cumsum(self._trace_len)[:-1]]).astype(np.int64)
        self._flat = np.ascontiguousarray(np.concatenate(tables, axis=0))

    def _reset_envs(self, idx: np.ndarray, coverage: float) -> None:
        """Start new episodes for the plants ``idx`` at NH3 coverage ``coverage`` (in place; writes their
        observations)."""
        b = self._batch
        rng = self.np_random
        for i in idx:
            key = self._cycle_keys[i]
            cfg = self._configs[key]
            if is_random_cycle(cfg.cycle):
                pool = self._pool_index[cfg.cycle]
                t = pool[int(rng.integers(len(pool)))]
            else:
                t = self._fixed_index[key]
            self._env_trace[i] = t
            length = int(self._trace_len[t])
            offset = int(rng.integers(0, max(length // 2, 1))) if self.random_offsets else 0
            self._base[i] = self._trace_base[t] + offset
            self._len[i] = length - offset if self.max_episode_steps is None else min(length - offset,
                                                                                      self.max_episode_steps)
            self._k[i] = 0
            self._autoreset[i] = False
            # a cold start only at the start of the cycle; a random offset starts mid-cycle, warm
            b.start_episode(int(i), cfg, rng, self._base_params, self._flat[self._base[i]],
                            cfg.cold_start and offset == 0, coverage)

    # ----------------------------------------------------------------------------------------------- API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        # every option is checked before anything changes (a failed reset leaves the generator and plants as they were)
        options = reset_options(options, RESET_OPTIONS)
        coverage = reset_coverage(options, self.config.initial_coverage)
        rebuild = seed is not None or not self._rng_ready
        mask = options.get("reset_mask")
        if mask is None:
            idx = np.arange(self.num_envs)
        else:
            expected = (f"options['reset_mask'] must be a boolean array of shape ({self.num_envs},) (True: reset that "
                        f"env; for env indices i use np.isin(np.arange(num_envs), i))")
            try:
                mask_arr = np.asarray(mask)
            except (TypeError, ValueError):
                raise ValueError(f"{expected}, got {mask!r}") from None
            if mask_arr.dtype != np.bool_ or mask_arr.shape != (self.num_envs,):
                raise ValueError(f"{expected}, got dtype {mask_arr.dtype} and shape {mask_arr.shape}")
            idx = np.flatnonzero(mask_arr)
            if rebuild and idx.size != self.num_envs:
                raise ValueError("options['reset_mask'] must select every env on the first reset and whenever a seed "
                                 "is given (the cycles of all envs are rebuilt from the seed)")
        super().reset(seed=seed)
        if rebuild:
            self._build_traces(np.random.default_rng(self.np_random.integers(0, 2**63 - 1)))
            self._rng_ready = True
        self._reset_envs(idx, coverage)
        self._needs_reset = False
        names = np.array([self._traces[t].name for t in self._env_trace], dtype=object)
        return self._batch.obs.copy(), {"cycle": names, "_cycle": self._ones.copy()}

    def _action_array(self, actions: Any) -> np.ndarray:
        """``actions`` as a float (num_envs,) array (values unchecked)."""
        a = np.asarray(actions)
        if a.dtype != np.float32 and a.dtype != np.float64:
            if a.dtype.kind not in "fiu":
                raise ValueError(f"actions must be real numbers (a float or int array of shape ({self.num_envs}, 1)), "
                                 f"got dtype {a.dtype}")
            a = a.astype(np.float64)
        if a.shape not in ((self.num_envs, 1), (self.num_envs,)):
            raise ValueError(f"actions must have shape ({self.num_envs}, 1), got {a.shape}")
        return a.reshape(self.num_envs)

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
        if self._needs_reset:
            raise RuntimeError("call reset() before step()")
        a = self._action_array(actions)
        n = self.num_envs
        info = np.empty((7, n))  # rows: nox, nh3, adblue cost, tailpipe NOx, NH3 ppm, reward, AdBlue g/s
        step_index = np.empty(n, dtype=np.int64)
        truncated = np.empty(n, dtype=bool)
        b = self._batch
        restarting = np.flatnonzero(self._autoreset)  # NEXT_STEP: the plants whose episode ended last step
        skip = self._no_skip
        if restarting.size:
            if not np.all(np.isfinite(a)):  # checked before the resets change anything, as the step itself does
                raise ValueError(f"actions must be finite; NaN or inf at envs {np.flatnonzero(~np.isfinite(a))[:10]}")
            skip = self._autoreset.copy()
            self._reset_envs(restarting, self.config.initial_coverage)
        status = b.vector_step(a, self._normalized_actions, self.max_rate_g_s, self._flat, self._base, self._k,
                               self._len, self._row, self.np_random, self._noise, self.dt, info, step_index, truncated,
                               skip)
        if status < 0:
            raise ValueError(f"actions must be finite; NaN or inf at envs {np.flatnonzero(~np.isfinite(a))[:10]}")
        ended = status > 0
        terminated = np.zeros(n, dtype=bool)
        mask = self._ones if not restarting.size else ~skip
        infos: dict[str, Any] = {
            "nox_cost": info[0], "_nox_cost": mask,
            "nh3_cost": info[1], "_nh3_cost": mask,
            "adblue_cost": info[2], "_adblue_cost": mask,
            "tailpipe_nox_ppm": info[3], "_tailpipe_nox_ppm": mask,
            "tailpipe_nh3_ppm": info[4], "_tailpipe_nh3_ppm": mask,
            "adblue_g_s": info[6], "_adblue_g_s": mask,
            "step_index": step_index, "_step_index": mask,
        }
        if restarting.size:
            names = np.full(n, None, dtype=object)
            for i in restarting:
                names[i] = self._traces[self._env_trace[i]].name
            infos["cycle"] = names
            infos["_cycle"] = skip
        rewards = info[5]
        if ended:
            ended_idx = np.flatnonzero(truncated)
            ended_mask = np.zeros(n, dtype=bool)
            ended_mask[ended_idx] = True
            kpis = self._kpi_info(ended_idx)
            if self.autoreset_mode == AutoresetMode.NEXT_STEP:
                infos["episode_kpis"] = kpis
                infos["_episode_kpis"] = ended_mask
                self._autoreset[ended_idx] = True
            else:
                final_obs = np.full(n, None, dtype=object)
                for i in ended_idx:
                    final_obs[i] = b.obs[i].copy()
                infos["final_obs"] = final_obs
                infos["_final_obs"] = ended_mask
                infos["final_info"] = {"episode_kpis": kpis, "_episode_kpis": ended_mask}
                infos["_final_info"] = ended_mask
                self._reset_envs(ended_idx, self.config.initial_coverage)
        return b.obs.copy(), rewards, terminated, truncated, infos

    def _kpi_info(self, ended_idx: np.ndarray) -> dict[str, np.ndarray]:
        """The ended plants' KPIs as VectorEnv._add_info builds them from {"episode_kpis": kpis} env by env (float64
        arrays, each key with its own mask), built at once as rows of two arrays."""
        n = self.num_envs
        kpis = [self._kpis_of(int(i)) for i in ended_idx]
        keys = list(kpis[0])
        values = np.zeros((len(keys), n))
        values[:, ended_idx] = np.array([[k[key] for k in kpis] for key in keys])
        masks = np.zeros((len(keys), n), dtype=bool)
        masks[:, ended_idx] = True
        per_key: dict[str, Any] = {}
        for j, key in enumerate(keys):
            per_key[key] = values[j]
            per_key[f"_{key}"] = masks[j]
        return per_key

    def _kpis_of(self, i: int) -> dict[str, float]:
        b = self._batch
        acc = b.acc[i]
        # NH3 stored now: the plant step's figure, or at the start of the episode (no step yet) the initial one
        stored = float(b.out[i, K.O_STORED]) if acc[core.A_STEPS] > 0 else float(acc[core.A_STORED0_MOL])
        return core.episode_kpis(acc, stored)

    def episode_kpis(self) -> list[dict[str, float]]:
        """The KPIs of every plant's current episode so far (:func:`scr_env.envs.kpis.episode_kpis`), one dict per
        plant: after any number of steps, e.g. when a wrapper or the caller ends the episodes early. RuntimeError
        before the first ``reset``."""
        if self._needs_reset:
            raise RuntimeError("episode_kpis() needs an episode: call reset() first")
        return [self._kpis_of(i) for i in range(self.num_envs)]

    @property
    def state(self) -> dict[str, np.ndarray]:
        """Privileged states of all plants (copies): coverages and temperatures, shape (num_envs, n_cells)."""
        return {"nh3_coverage": self._batch.theta.copy(), "temperature_k": self._batch.temperature_k.copy()}

    @property
    def catalyst_params_array(self) -> np.ndarray:
        """Packed parameters of every plant's catalyst in this episode (after ageing and randomisation), shape
        (num_envs, len(scr_env.params.PACKED_FIELDS)) (a copy)."""
        return self._batch.cat_params.copy()

    def close_extras(self, **kwargs: Any) -> None:
        pass


