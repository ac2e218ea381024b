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
  silence judged on what was received, not on when this process looked.
"""
from .verdict import OK, Action, Verdict
from .wrench import ForcePrediction, LoadPrediction, PlatformWrench, WrenchTiers, wrench_axis

__all__ = ['Action', 'Verdict', 'OK', 'PlatformWrench', 'LoadPrediction', 'WrenchTiers',
           'ForcePrediction', 'wrench_axis']
