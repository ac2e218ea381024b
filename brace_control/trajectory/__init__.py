"""Motion profiles and limit-respecting planning (pure numpy/scipy/ruckig: no ROS).

>>> from brace_control.trajectory import MinimumJerk
>>> tr = MinimumJerk([0.0, 0.39, 0.0], [0.02, 0.40, 0.05], 1.0)
>>> p, v, a = tr.sample(0.5)

* :class:`MinimumJerk`, :class:`ViaPointMinimumJerk`: Flash–Hogan, thesis 002 eqs. (2.2)–(2.11);
  :func:`fitts_duration`: eq. (2.12).
* :class:`SCurve`: time-optimal jerk-limited (Ruckig), robust to Ruckig's boundary errors.
* :class:`LogCosh`: the shoulder thesis's log-cosh S-curve (seed 004), exact at both ends.
* :func:`plan_motion`: a profile checked along its path against a mechanism
  (:mod:`.limits`), slowed down or rejected with the reason.
* :class:`KnotTrajectory`, :func:`knots_of`: a motion as knots (quintic Hermite), the way it
  travels between the nodes; :func:`actuator_knots`: the same in actuator coordinates.
* :class:`TrajectoryRunner`: goals, preemption, cancel and status, for the node.
"""
from .actuator import ACTUATOR_TOLERANCE, UnreachableKnot, actuator_knots
from .base import MotionState, PiecewisePolynomial, Trajectory, TrajectoryError
from .hermite import KnotTrajectory
from .knots import knots_of, refine
from .limits import Limits, PathCheck, Violation, check_capacity, check_path, check_pose
from .logcosh import LogCosh
from .minimum_jerk import FittsLaw, MinimumJerk, ViaPointMinimumJerk, brake, fitts_duration
from .planner import Plan, PlanRejected, Profile, load_planning_modules, plan_motion
from .poses import PoseError, arrival_times
from .runner import GoalEvent, GoalRequest, GoalState, StartState, TrajectoryRunner
from .scurve import SCurve

__all__ = [
    'Trajectory', 'PiecewisePolynomial', 'MotionState', 'TrajectoryError', 'KnotTrajectory',
    'knots_of', 'refine', 'actuator_knots', 'ACTUATOR_TOLERANCE', 'UnreachableKnot',
    'MinimumJerk', 'ViaPointMinimumJerk', 'SCurve', 'LogCosh', 'fitts_duration', 'FittsLaw',
    'brake', 'Limits', 'Violation', 'PathCheck', 'check_path', 'check_pose', 'check_capacity',
    'Profile', 'Plan', 'PlanRejected', 'plan_motion', 'load_planning_modules',
    'GoalState', 'GoalRequest', 'GoalEvent', 'StartState', 'TrajectoryRunner',
    'PoseError', 'arrival_times',
]
