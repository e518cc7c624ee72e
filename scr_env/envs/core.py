"""Machinery shared by the single and the vector environment: one compiled step for B plants.

The per-plant step (``_one``) advances one plant by one control interval (the physics of
:mod:`scr_env.physics.kernel`), then computes, still in compiled code, its reward terms, the episode KPI accumulators
and the observation. The single environment runs it for B = 1 (:meth:`PlantBatch.step`), the vector environment for
B = num_envs together with its action, noise and bookkeeping work (:meth:`PlantBatch.vector_step`), serially or on
all threads, whichever is faster at the moment; neither has its own copy of the physics.
"""
from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

import numba
import numpy as np

from scr_env.cycles import ExhaustTrace
from scr_env.envs.kpis import (  # noqa: F401  (the reward and KPI names, re-exported where they were defined)
    A_ADBLUE_G,
    A_ENGINE_NOX_G,
    A_N2O_G,
    A_N_IN_MOL,
    A_N_OUT_MOL,
    A_NH3_G,
    A_NH3_PEAK_PPM,
    A_NH3_PPM_S,
    A_STEPS,
    A_STORED0_MOL,
    A_TAILPIPE_NOX_G,
    A_TIME_S,
    A_UREA_N_MOL,
    A_WORK_KWH,
    N_ACC,
    N_TERMS,
    REWARD_TERMS,
    RewardWeights,
    account_command,
    account_step,
    episode_kpis,
)
from scr_env.jit import njit
from scr_env.params import P, pack
from scr_env.physics import kernel as K
from scr_env.physics.backends import actuator_step_nb

if TYPE_CHECKING:
    from scr_env.envs.config import EnvConfig

# columns of the per-step drive table built from an ExhaustTrace (kernel inputs plus engine power)
DRIVE_FIELDS = ("exhaust_flow_mol_s", "inlet_temperature_k", "inlet_nox_ppm", "inlet_no2_fraction",
                "engine_power_kw", "o2_fraction")
D_FLOW, D_TIN, D_NOX, D_NO2F, D_POWER, D_O2 = range(len(DRIVE_FIELDS))

# observation layout
OBS_BASE = ("upstream_nox_ppm", "inlet_temperature_k", "exhaust_flow_mol_s", "tailpipe_nox_sensor_ppm",
            "previous_action")
OBS_BASE_LOW = (0.0, 0.0, 0.0, 0.0, -1.0)
OBS_BASE_HIGH = (10000.0, 1500.0, 100.0, 10000.0, 1.0)
NH3_SENSOR_HIGH = 10000.0
_P_SITES = P["sites_per_cell_mol"]


def drive_table(trace: ExhaustTrace, o2_fraction: float) -> np.ndarray:
    """(n_steps, 6) float64 table: flow, inlet temperature, NOx, NO2 fraction, engine power, O2 per step."""
    return np.ascontiguousarray(np.column_stack([
        trace.exhaust_flow_mol_s, trace.scr_inlet_temperature_k, trace.nox_ppm, trace.no2_fraction,
        trace.engine_power_kw, np.full(trace.n_steps, o2_fraction)]))


# Per plant, everything is indexed [b, j] on the (B, ...) blocks, never through row views, and compiled without
# reference counting (see the note at kernel._NO_REFCOUNT).
@njit(nogil=True, error_model="numpy", fastmath=set(K.FASTMATH), inline="always")
def _post_one(b, inputs, power_kw, dt, out, action_norm, weights, terms, reward, acc, obs, nh3_sensor, privileged,
              theta):
    account_step(b, inputs, power_kw, dt, out, weights, terms, reward, acc)
    obs[b, 0] = min(out[b, K.O_UPSTREAM_NOX], 10000.0)
    obs[b, 1] = min(max(out[b, K.O_TIN_SENSOR], 0.0), 1500.0)
    obs[b, 2] = min(out[b, K.O_FLOW_EST], 100.0)
    obs[b, 3] = min(out[b, K.O_NOX_SENSOR], 10000.0)
    obs[b, 4] = action_norm[b]
    i = 5
    if nh3_sensor:
        obs[b, i] = min(out[b, K.O_NH3_SENSOR], NH3_SENSOR_HIGH)
        i += 1
    if privileged:
        for j in range(theta.shape[1]):
            obs[b, i + j] = min(max(theta[b, j], 0.0), 1.0)


_N_INPUTS = len(K.INPUT_FIELDS)
_N_OUTPUTS = len(K.OUTPUT_FIELDS)
# the actuator block of a plant: delivered AdBlue rate [g/s], lag coefficient [-], largest change per step [g/s],
# enabled (1.0) or not (0.0: the command is delivered as it is) -- scr_env.actuator
ACTUATOR_FIELDS = ("delivered_g_s", "lag_coefficient", "max_change_g_s", "enabled")
N_ACTUATOR = len(ACTUATOR_FIELDS)
ACT_DELIVERED, ACT_LAG, ACT_MAX_CHANGE, ACT_ENABLED = range(N_ACTUATOR)


@njit(nogil=True, error_model="numpy", fastmath=set(K.FASTMATH), inline="always")
def _blocks(buf, lay):
    """The column blocks of the buffer, as (B, width) views (free without reference counting); order of
    :data:`_BLOCKS`."""
    n = lay[0]
    return (buf[:, lay[1]:lay[1] + n], buf[:, lay[2]:lay[2] + n], buf[:, lay[3]:lay[3] + K.N_SENSOR_STATES],
            buf[:, lay[4]:lay[4] + _N_INPUTS], buf[:, lay[5]], buf[:, lay[6]:lay[6] + K.N_PACKED],
            buf[:, lay[7]:lay[7] + K.N_AUX], buf[:, lay[8]:lay[8] + K.N_NOISE], buf[:, lay[9]:lay[9] + _N_OUTPUTS],
            buf[:, lay[10]], buf[:, lay[11]:lay[11] + N_TERMS], buf[:, lay[12]:lay[12] + N_TERMS], buf[:, lay[13]],
            buf[:, lay[14]:lay[14] + N_ACC], buf[:, lay[15]:lay[15] + N_ACTUATOR])


# The parallel loops call it with np.int64(b): a prange index is unsigned, and numba would compile a second copy of
# the whole plant step for it (seconds of a cold start).
@njit(**K._NO_REFCOUNT)
def _one(b, buf, lay, obs, drive, row_idx, noise_tab, noise_idx, dt):
    # few arguments on purpose: each array argument is a 7-word struct passed on the stack
    (theta, temp, sens, inputs, power, cat_p, aux_p, noise, out, action_norm, weights, terms, reward,
     acc, act) = _blocks(buf, lay)
    r = row_idx[b]
    inputs[b, K.I_FLOW] = drive[r, D_FLOW]
    inputs[b, K.I_TIN] = drive[r, D_TIN]
    inputs[b, K.I_NOX] = drive[r, D_NOX]
    inputs[b, K.I_NO2F] = drive[r, D_NO2F]
    inputs[b, K.I_O2] = drive[r, D_O2]
    power[b] = drive[r, D_POWER]
    m = noise_idx[b]
    for i in range(K.N_NOISE):
        noise[b, i] = noise_tab[m, i]
    # the dosing unit (scr_env.actuator): the command in inputs[b, I_ADBLUE] becomes the rate it delivers
    command = inputs[b, K.I_ADBLUE]
    account_command(b, command, acc)
    if act[b, ACT_ENABLED] != 0.0:
        delivered = actuator_step_nb(command, act[b, ACT_DELIVERED], act[b, ACT_LAG], act[b, ACT_MAX_CHANGE])
        act[b, ACT_DELIVERED] = delivered
        inputs[b, K.I_ADBLUE] = delivered
    K._plant_step_one(b, theta, temp, sens, inputs, dt, cat_p, aux_p, noise, out)
    _post_one(b, inputs, power, dt, out, action_norm, weights, terms, reward, acc, obs, lay[16] != 0, lay[17] != 0,
              theta)


@njit(nogil=True, error_model="numpy", fastmath=set(K.FASTMATH))
def _env_step_serial(buf, lay, obs, drive, row_idx, noise_tab, noise_idx, dt):
    for b in range(buf.shape[0]):
        _one(b, buf, lay, obs, drive, row_idx, noise_tab, noise_idx, dt)


@njit(nogil=True, error_model="numpy", fastmath=set(K.FASTMATH), parallel=True)
def _env_step_parallel(buf, lay, obs, drive, row_idx, noise_tab, noise_idx, dt):
    for b in numba.prange(buf.shape[0]):
        _one(np.int64(b), buf, lay, obs, drive, row_idx, noise_tab, noise_idx, dt)


# fastmath=False stated: numba would otherwise compile it with its caller's fast-math flags, and contracted
# floating point in the ziggurat's accept tests could part from numpy's draws
@njit(nogil=True, fastmath=False)
def standard_normal_fill(rng, out):
    """``rng.standard_normal(out=out)`` for a C-contiguous ``out``, in compiled code: numba implements numpy's
    ziggurat on the same bit generator, so the values and the generator state afterwards are numpy's (checked by a
    test), at about 60 % of numpy's time (40 vs 65 us for 1024 x 5 draws)."""
    flat = out.reshape(-1)
    for i in range(flat.size):
        flat[i] = rng.standard_normal()


# The vector environment's per-step bookkeeping, compiled: numpy would make a dozen temporaries of B elements.
@njit(nogil=True, error_model="numpy", fastmath=set(K.FASTMATH))
def apply_actions(actions, normalized, max_rate_g_s, buf, col_adblue, col_action, rate_out):
    """Clip a batch of actions (shape (B,)) and write the AdBlue rate [g/s] (to the buffer column ``col_adblue`` and
    ``rate_out``) and the normalised action (to ``col_action``). Returns the number of non-finite actions; if there
    are any, nothing is written."""
    n = actions.shape[0]
    bad = 0
    for i in range(n):
        if not math.isfinite(actions[i]):
            bad += 1
    if bad > 0:
        return bad
    for i in range(n):
        v = float(actions[i])
        if normalized:
            norm = min(max(v, -1.0), 1.0)
            rate = 0.5 * (norm + 1.0) * max_rate_g_s
        else:
            rate = min(max(v, 0.0), max_rate_g_s)
            norm = 2.0 * rate / max_rate_g_s - 1.0
        buf[i, col_adblue] = rate
        buf[i, col_action] = norm
        rate_out[i] = rate
    return 0


@njit(nogil=True, error_model="numpy", fastmath=set(K.FASTMATH))
def vector_outputs(buf, lay, k, length, info, step_index, truncated, skip):
    """After a step: advance the step counters ``k``, set ``truncated`` (k >= length) and ``step_index`` (= k), and
    fill ``info`` rows 0-5 with nox, nh3 and adblue cost, tailpipe NOx and NH3 [ppm] and the reward. Plants with
    ``skip[b]`` did not step (their autoreset step): counters kept, not truncated, info rows 0. Returns whether any
    plant's cycle ended."""
    out = buf[:, lay[9]:lay[9] + _N_OUTPUTS]
    terms = buf[:, lay[12]:lay[12] + N_TERMS]
    reward = buf[:, lay[13]]
    ended = False
    for b in range(buf.shape[0]):
        if skip[b]:
            step_index[b] = k[b]
            truncated[b] = False
            for r in range(6):
                info[r, b] = 0.0
            info[6, b] = 0.0
            continue
        kb = k[b] + 1
        k[b] = kb
        step_index[b] = kb
        t = kb >= length[b]
        truncated[b] = t
        ended |= t
        info[0, b] = terms[b, 0]
        info[1, b] = terms[b, 1]
        info[2, b] = terms[b, 2]
        info[3, b] = out[b, K.O_NO] + out[b, K.O_NO2]
        info[4, b] = out[b, K.O_NH3]
        info[5, b] = reward[b]
        info[6, b] = buf[b, lay[4] + K.I_ADBLUE]  # the rate delivered (the command unless an actuator lags it)
    return ended


@njit(nogil=True, error_model="numpy", fastmath=set(K.FASTMATH))
def _vector_prologue(actions, normalized, max_rate_g_s, buf, lay, base, k, row, rng, noise, rate_out):
    """Actions into the buffer, drive rows ``base + k``, sensor noise drawn; returns the number of non-finite
    actions (then nothing is written and no noise is drawn)."""
    bad = apply_actions(actions, normalized, max_rate_g_s, buf, lay[4] + K.I_ADBLUE, lay[10], rate_out)
    if bad > 0:
        return bad
    for b in range(buf.shape[0]):
        row[b] = base[b] + k[b]
    standard_normal_fill(rng, noise)
    return 0


# One compiled call per vector-env step (each numba call costs a few microseconds of argument checks, and the
# Python glue between calls as much again): actions, noise, the plants, the bookkeeping. Plants with skip[b] are not
# stepped (Gymnasium's NEXT_STEP autoreset: they were just reset). Returns -(number of non-finite actions) if there
# are any (nothing done), else 1 if a plant's cycle ended, else 0.
@njit(nogil=True, error_model="numpy", fastmath=set(K.FASTMATH))
def vector_step_serial(actions, normalized, max_rate_g_s, buf, lay, obs, drive, base, k, length, row, rng, noise,
                       noise_idx, dt, info, step_index, truncated, skip):
    bad = _vector_prologue(actions, normalized, max_rate_g_s, buf, lay, base, k, row, rng, noise, info[6])
    if bad > 0:
        return -bad
    for b in range(buf.shape[0]):
        if not skip[b]:
            _one(b, buf, lay, obs, drive, row, noise, noise_idx, dt)
    return 1 if vector_outputs(buf, lay, k, length, info, step_index, truncated, skip) else 0


@njit(nogil=True, error_model="numpy", fastmath=set(K.FASTMATH), parallel=True)
def vector_step_parallel(actions, normalized, max_rate_g_s, buf, lay, obs, drive, base, k, length, row, rng, noise,
                         noise_idx, dt, info, step_index, truncated, skip):
    bad = _vector_prologue(actions, normalized, max_rate_g_s, buf, lay, base, k, row, rng, noise, info[6])
    if bad > 0:
        return -bad
    for b in numba.prange(buf.shape[0]):
        if not skip[b]:
            _one(np.int64(b), buf, lay, obs, drive, row, noise, noise_idx, dt)
    return 1 if vector_outputs(buf, lay, k, length, info, step_index, truncated, skip) else 0


# column blocks of the PlantBatch buffer: (name, width or None for n_cells)
_BLOCKS = (("theta", None), ("temperature_k", None), ("sensor_state", K.N_SENSOR_STATES),
           ("inputs", _N_INPUTS), ("power_kw", 1), ("cat_params", K.N_PACKED), ("aux_params", K.N_AUX),
           ("noise", K.N_NOISE), ("out", _N_OUTPUTS), ("action_norm", 1), ("weights", N_TERMS),
           ("terms", N_TERMS), ("reward", 1), ("acc", N_ACC), ("actuator", N_ACTUATOR))


class _ThreadingChooser:
    """Picks the serial or the multi-threaded batch step from their measured wall times.

    Both give bitwise the same result (plants are independent; each is computed by the same code on one thread).
    On an idle machine the threaded step is about num_threads times faster, but when other processes keep the
    cores busy, a static split over threads waits for the slowest, descheduled one and can be several times slower
    than the serial loop (measured at load 3.7 on 2 cores: 160 k vs 400 k env-steps/s at 1024 envs). So the step
    keeps a running estimate of the time of each variant, runs the faster one, and re-times the other every
    ``PROBE_EVERY`` steps (the first call of each is skipped: it may include JIT compilation or cache loading).
    The estimate follows a faster time at once and a slower one gradually, so one slow outlier (a descheduled
    thread) does not keep the step on the slower variant for many probes.

    A re-timing that leaves the choice as it was doubles the interval to the next one, up to ``MAX_PROBE_EVERY``
    steps; a re-timing that changes the choice sets it back to ``PROBE_EVERY``. On a busy machine the threaded
    step took about 7.6 ms against the serial loop's 1.7 ms (1024 envs, 2 cores at load 3), so a probe every 64
    steps cost 5 % of the throughput; with the back-off it costs under 1 %, and a change of load is still
    noticed within ``MAX_PROBE_EVERY`` steps (under a second at 1024 envs).

    The serial variant runs first: its machine code is mostly the per-plant step, which any step needs, so the first
    step compiles little else; the threaded variant is compiled when it is first probed (the third step). With one
    numba thread (``NUMBA_NUM_THREADS=1``) there is nothing to choose: the chooser is not used.
    """

    PROBE_EVERY = 64  # steps between re-timings of the slower variant [chosen: costs ~1 % when it is 2x slower]
    MAX_PROBE_EVERY = 512  # longest interval after re-timings that kept the choice [chosen: < 1 % at 4x slower]
    SMOOTHING = 0.25  # weight of a slower new timing in the running estimate [-] [chosen]

    def __init__(self) -> None:
        self.mean_s = [math.inf, math.inf]  # serial, threaded
        self.calls = [0, 0]
        self.since_probe = 0
        self.probe_every = self.PROBE_EVERY  # steps to the next re-timing (doubles while the choice holds)
        self._probed_best = -1  # the choice at the re-timing now running, or -1 when none is

    def best(self) -> int:
        """The variant with the smaller running estimate (1 threaded, 0 serial)."""
        return 1 if self.mean_s[1] <= self.mean_s[0] else 0

    def pick(self) -> int:
        """1 for the threaded step, 0 for the serial one."""
        if self.calls[0] < 2:
            return 0
        if self.calls[1] < 2:
            return 1
        best = self.best()
        self.since_probe += 1
        if self.since_probe >= self.probe_every:
            self.since_probe = 0
            self._probed_best = best
            return 1 - best
        return best

    def record(self, mode: int, seconds: float) -> None:
        self.calls[mode] += 1
        if self.calls[mode] == 1:
            return
        m = self.mean_s[mode]
        self.mean_s[mode] = seconds if seconds < m else m + self.SMOOTHING * (seconds - m)
        if self._probed_best >= 0:  # the re-timing of the slower variant
            kept = self.best() == self._probed_best
            self.probe_every = min(2 * self.probe_every, self.MAX_PROBE_EVERY) if kept else self.PROBE_EVERY
            self._probed_best = -1


class PlantBatch:
    """State and work arrays of B plants, and the one call that steps them (:meth:`step`).

    All float64 arrays are column blocks of one buffer (so the compiled step takes few arguments); the attributes
    ``theta``, ``temperature_k``, ``inputs``, ``out``, ``acc`` ... are writable views of it.
    """

    def __init__(self, n: int, n_cells: int, obs_dim: int, nh3_sensor: bool, privileged: bool) -> None:
        self.n = n
        offsets = []
        col = 0
        for _name, width in _BLOCKS:
            offsets.append(col)
            col += n_cells if width is None else width
        self.buf = np.zeros((n, col))
        self.layout = np.array([n_cells, *offsets, int(bool(nh3_sensor)), int(bool(privileged))], dtype=np.int64)
        for (name, width), off in zip(_BLOCKS, offsets, strict=True):
            w = n_cells if width is None else width
            setattr(self, name, self.buf[:, off] if width == 1 else self.buf[:, off:off + w])
        self.obs = np.zeros((n, obs_dim), dtype=np.float32)
        self.nh3_sensor = bool(nh3_sensor)
        self.privileged = bool(privileged)
        threads = numba.config.NUMBA_NUM_THREADS > 1
        self._chooser = _ThreadingChooser() if n >= K.PARALLEL_MIN_BATCH and threads else None
        self._noise_rows = np.arange(n, dtype=np.int64)
        self.col_adblue = offsets[3] + K.I_ADBLUE
        self.col_action = offsets[9]
        self.col_reward = offsets[12]

    def set_actuator(self, actuator: Any, dt: float) -> None:
        """Every plant behind ``actuator`` (:class:`scr_env.actuator.ActuatorParams`, or None for ideal dosing)."""
        if actuator is None:
            self.actuator[:] = 0.0
            return
        self.actuator[:, ACT_LAG] = actuator.lag_coefficient(dt)
        self.actuator[:, ACT_MAX_CHANGE] = actuator.max_change_g_s(dt)
        self.actuator[:, ACT_ENABLED] = 1.0

    def step(self, dt: float, drive: np.ndarray, row_idx: np.ndarray, noise_tab: np.ndarray,
             noise_idx: np.ndarray) -> None:
        """Advance every plant by ``dt``: plant b reads row ``row_idx[b]`` of ``drive`` (flow, inlet temperature,
        NOx, NO2 fraction, power, O2) and noise row ``noise_idx[b]`` of ``noise_tab``; the AdBlue rate and
        normalised action must already be in ``inputs[:, I_ADBLUE]`` and ``action_norm``."""
        chooser = self._chooser
        if chooser is None:
            if self.n == 1:  # the single environment: the per-plant step itself (one compiled function less)
                _one(0, self.buf, self.layout, self.obs, drive, row_idx, noise_tab, noise_idx, dt)
            else:
                _env_step_serial(self.buf, self.layout, self.obs, drive, row_idx, noise_tab, noise_idx, dt)
            return
        mode = chooser.pick()
        start = time.perf_counter()
        (_env_step_parallel if mode else _env_step_serial)(self.buf, self.layout, self.obs, drive, row_idx, noise_tab,
                                                           noise_idx, dt)
        chooser.record(mode, time.perf_counter() - start)

    def vector_step(self, actions: np.ndarray, normalized: bool, max_rate_g_s: float, drive: np.ndarray,
                    base: np.ndarray, k: np.ndarray, length: np.ndarray, row: np.ndarray, rng: np.random.Generator,
                    noise: np.ndarray, dt: float, info: np.ndarray, step_index: np.ndarray,
                    truncated: np.ndarray, skip: np.ndarray) -> int:
        """The vector environment's step in one compiled call (see :func:`vector_step_serial`): ``actions`` (B,)
        raw, plant b on drive row ``base[b] + k[b]`` (written to ``row``) and noise row b of ``noise`` (drawn from
        ``rng``); advances ``k``; fills ``info`` (7, B), ``step_index`` and ``truncated``; plants with ``skip[b]``
        are left as they are. Returns -(number of non-finite actions) if any (nothing done), else 1 if a cycle
        ended, else 0."""
        args = (actions, normalized, max_rate_g_s, self.buf, self.layout, self.obs, drive, base, k, length, row, rng,
                noise, self._noise_rows, dt, info, step_index, truncated, skip)
        chooser = self._chooser
        if chooser is None:
            return vector_step_serial(*args)
        mode = chooser.pick()
        start = time.perf_counter()
        status = (vector_step_parallel if mode else vector_step_serial)(*args)
        chooser.record(mode, time.perf_counter() - start)
        return status

    def start_episode(self, i: int, config: EnvConfig, rng: np.random.Generator, base_params: np.ndarray,
                      first_row: np.ndarray, cold: bool, coverage: float) -> None:
        """Begin an episode of plant ``i``: the one reset of the single and the vector environment.

        The catalyst is ``base_params`` (packed), or with ``config.randomize`` or an ``age_h`` range a new draw from
        ``rng`` (:meth:`EnvConfig.episode_catalyst`); every cell at NH3 coverage ``coverage`` and at ambient
        temperature (``cold``) or at the inlet temperature of ``first_row`` (a row of
        :func:`drive_table`); the sensors settled on that row's readings (no NH3), the accumulators at zero, and the
        observation before the first step (previous action -1, no dosing).
        """
        if config.randomizes:
            self.cat_params[i] = pack(config.episode_catalyst(rng))
        else:
            self.cat_params[i] = base_params
        t0 = float(first_row[D_TIN])
        nox0 = float(first_row[D_NOX])
        no2f0 = float(first_row[D_NO2F])
        self.theta[i] = coverage
        self.temperature_k[i] = config.catalyst.ambient_temperature_k if cold else t0
        self.sensor_state[i] = (nox0 * (1.0 - no2f0) + config.sensors.nox_sensor_no2_gain * nox0 * no2f0, 0.0, t0)
        self.acc[i] = 0.0
        self.actuator[i, ACT_DELIVERED] = 0.0  # no dosing before the episode
        self.acc[i, A_STORED0_MOL] = float(self.theta[i].sum() * self.cat_params[i, _P_SITES])
        self.initial_observation(i, nox0, t0, float(first_row[D_FLOW]), -1.0)

    def initial_observation(self, b: int, upstream_nox_ppm: float, inlet_temperature_k: float, flow_mol_s: float,
                            action_norm: float) -> None:
        """Observation before the first step: sensors at their initial states."""
        ob = self.obs[b]
        ob[0] = min(max(upstream_nox_ppm, 0.0), 10000.0)
        ob[1] = min(max(inlet_temperature_k, 0.0), 1500.0)
        ob[2] = min(max(flow_mol_s, 0.0), 100.0)
        ob[3] = min(max(self.sensor_state[b, 0], 0.0), 10000.0)
        ob[4] = action_norm
        i = 5
        if self.nh3_sensor:
            ob[i] = 0.0
            i += 1
        if self.privileged:
            ob[i:i + self.theta.shape[1]] = np.clip(self.theta[b], 0.0, 1.0)
