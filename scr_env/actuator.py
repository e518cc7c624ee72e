"""The optional dosing actuator of the environments: what a real dosing unit delivers for a commanded AdBlue rate.

An RL policy may command a dose that jumps between 0.2 and 2.5 g/s from one 0.5 s step to the next (the shipped SAC
does on the WHSC). A dosing unit does not deliver that: its supply pump holds the line pressure with a controller of
its own, the dosing valve is pulsed (PWM) at a few hertz, and the spray has to evaporate and reach the catalyst
face, part of it via a wall film. :class:`ActuatorParams` lumps this into

* a **first-order lag** of the delivered rate towards the command, time constant ``time_constant_s``;
* a **slew limit** of the delivered rate, ``max_slew_g_s2`` [g/s per s].

Per control interval ``dt`` (:func:`scr_env.physics.dosing.actuator_step`, compiled into the plant step)::

    delivered += clip((1 - exp(-dt / time_constant_s)) * (command - delivered), -max_slew_g_s2 dt, +max_slew_g_s2 dt)

The delivered rate starts at 0 g/s at every reset (no dosing before the episode). Everything the plant sees and the
KPIs count (NH3 formed, ``adblue_g``, the reward's AdBlue term, ``info["adblue_g_s"]``) is the delivered rate; the
observation's ``previous_action`` stays the command. Without an actuator (``actuator=None``, the environment's
default) the command is delivered at once, as before.

Defaults and their sources:

* ``time_constant_s`` = 1.0 s. [chosen, order of magnitude from the literature] Measured urea-flow-rate transients of
  a urea-SCR system show "very slow dynamics (on the order of seconds)" (Kim et al., Transactions of KSAE 15(3),
  2007, "Dynamic characteristics of a urea-SCR system"; koreascience JAKO200721138192070) -- that figure includes the
  catalyst; the dosing path (PWM period of the valve, spray evaporation, wall film) is the faster part of it. No
  public data sheet of a dosing unit (Bosch Denoxtronic 2.2/6-5, Continental, Albonair) states a delivered-rate time
  constant; they give the rate range and the injection frequency (1 to a few Hz), which bounds the lag from below at
  about one PWM period. 1 s is twice the control interval.
* ``max_slew_g_s2`` = 1.0 g/s per s. [chosen] The full range of the default injector (3 g/s,
  :class:`scr_env.params.DosingParams`) in 3 s: a pressure-controlled supply module ramps its delivery over about
  a second or more; it is also the rate limit the project's PI and NMPC controllers impose on themselves
  (``max_rate_change_g_s2`` = 1.0 in :mod:`control.baselines` and :mod:`control.mpc`), so those controllers are not
  changed by it.

Chatter: every episode's KPIs include the total variation of the commanded and of the delivered dose per hour
(``command_total_variation_g_s_per_h``, ``adblue_total_variation_g_s_per_h``: the sum of |rate(k) - rate(k-1)|
over the episode's steps [g/s], divided by its duration [h]), with or without an actuator
(:func:`scr_env.envs.kpis.episode_kpis`).
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

__all__ = ["DEFAULT_ACTUATOR", "ActuatorParams", "actuator_params"]


@dataclass(frozen=True)
class ActuatorParams:
    """A dosing unit's response to the commanded AdBlue rate (see the module docstring for the model and sources).

    ``time_constant_s`` [s] >= 0 (0: no lag); ``max_slew_g_s2`` [g/s per s] > 0 (``math.inf``: no slew limit).
    """

    time_constant_s: float = 1.0  # s [chosen, see the module docstring]
    max_slew_g_s2: float = 1.0  # g/s per s [chosen, see the module docstring]

    def __post_init__(self) -> None:
        for name in ("time_constant_s", "max_slew_g_s2"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(v):
                raise ValueError(f"actuator.{name} must be a number, got {v!r}")
        if not (math.isfinite(self.time_constant_s) and 0.0 <= self.time_constant_s <= 3600.0):
            raise ValueError(f"actuator.time_constant_s must be in [0, 3600] s, got {self.time_constant_s!r}")
        if not self.max_slew_g_s2 > 0.0:
            raise ValueError(f"actuator.max_slew_g_s2 must be > 0 g/s per s (inf: no limit), got "
                             f"{self.max_slew_g_s2!r}")

    def lag_coefficient(self, dt: float) -> float:
        """1 - exp(-dt / time_constant_s) [-] (1 without lag)."""
        return 1.0 if self.time_constant_s == 0.0 else -math.expm1(-dt / self.time_constant_s)

    def max_change_g_s(self, dt: float) -> float:
        """The largest change of the delivered rate in one interval [g/s] (inf without a slew limit)."""
        return self.max_slew_g_s2 * dt

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


#: the actuator of the benchmark tasks (``actuator="default"``)
DEFAULT_ACTUATOR = ActuatorParams()


def actuator_params(value: Any) -> ActuatorParams | None:
    """The environment's ``actuator`` argument as :class:`ActuatorParams` or None (ideal dosing): None or False for
    none; True or ``"default"`` for :data:`DEFAULT_ACTUATOR`; a dict of its fields; or an ActuatorParams. Anything
    else raises ``ValueError`` naming ``actuator``."""
    if value is None or value is False:
        return None
    if value is True or (isinstance(value, str) and value.strip().lower() == "default"):
        return DEFAULT_ACTUATOR
    if isinstance(value, ActuatorParams):
        return value
    if isinstance(value, Mapping):
        unknown = set(value) - {"time_constant_s", "max_slew_g_s2"}
        if unknown:
            raise ValueError(f"actuator has unknown keys {sorted(unknown)}; use time_constant_s, max_slew_g_s2")
        return ActuatorParams(**value)
    raise ValueError(f"actuator must be None, 'default', a dict with time_constant_s and max_slew_g_s2, or an "
                     f"ActuatorParams; got {value!r}")
