"""Protective functions as plain logic: no ROS, no bus (docs/safety.md).

Each function takes a sample and answers with a :class:`Verdict`: *ok*, *soft stop* (the
motion brakes along its path and holds, nothing latched) or *protective stop* (latched,
with a predicate that says whether its cause is still present). The CAN master evaluates
them in its SYNC cycle (:mod:`brace_control.can.monitors`); the nodes only report.

- :mod:`.verdict`: :class:`Action`, :class:`Verdict`;
- :mod:`.wrench`: the platform wrench from the load cells (:class:`PlatformWrench`), its
  hard and soft tiers (:class:`WrenchTiers`, docs/safety.md §8, §14), and the prediction the
  soft tiers share (:class:`LoadPrediction`), also applied to each actuator's load cell
  (:class:`ForcePrediction`);
- :mod:`.liveness`: heartbeats (§2), fresh feedback (§9) and an impossible measured speed (§8):
  silence judged on what was received, not on when this process looked;
- :mod:`.stroke`: a new target inside the stroke (:func:`stroke`, §5) and within the step
  limit (:func:`step_limit`, §7), whose bound :func:`max_step` ramps down near the stroke
  ends (§5);
- :mod:`.force`: an actuator's load cell at its saturation (:func:`saturation`, §9) or above
  the hard force limit (:func:`force_limit`, §8), and a motion pressing past the soft limit
  (:func:`pressing_past_soft_limit`, §14);
- :mod:`.tracking`: a position jump no actuator can make (:func:`position_jump`, §9) and a
  following error beyond the path tolerance (:func:`following_error`, §11).
"""
from .force import force_limit, pressing_past_soft_limit, saturation
from .stroke import max_step, step_limit, stroke
from .tracking import following_error, position_jump
from .verdict import OK, Action, Verdict
from .wrench import ForcePrediction, LoadPrediction, PlatformWrench, WrenchTiers, wrench_axis

__all__ = ['Action', 'Verdict', 'OK', 'PlatformWrench', 'LoadPrediction', 'WrenchTiers',
           'ForcePrediction', 'wrench_axis', 'max_step', 'stroke', 'step_limit', 'saturation',
           'force_limit', 'pressing_past_soft_limit', 'position_jump', 'following_error']
