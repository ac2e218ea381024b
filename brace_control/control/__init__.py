"""The control layer between the fieldbus and the nodes: pure numpy, no bus, no ROS.

- :mod:`.execution`: the trajectory executor the SYNC cycle samples (one time base for all
  axes, ros2_control's JointTrajectoryController semantics, braking along the path).

The CAN master (:mod:`brace_control.can`, CiA 301/402 transport) runs it in its cycle; the
protective tiers it answers to are in :mod:`brace_control.safety`.
"""
from .execution import (ActuatorTrajectory, ExecutionEvent, ExecutionState, PathExecutor,
                        TrajectoryInvalid)

__all__ = ['ActuatorTrajectory', 'ExecutionEvent', 'ExecutionState', 'PathExecutor', 'TrajectoryInvalid']
