"""Interaction control (admittance, zero-torque mode, wrench goals): pure numpy, no ROS.

See :mod:`.admittance` (the controller) and :mod:`.stability` (the loop model used to
choose the virtual mass and damping) and docs/interaction.md.
"""
from .admittance import AdmittanceController, AdmittanceParams, GoalRejected, LimitStop, Mode
from .stability import LoopModel, phase_margin, simulate_loop

__all__ = ['AdmittanceController', 'AdmittanceParams', 'GoalRejected', 'LimitStop', 'Mode',
           'LoopModel', 'phase_margin', 'simulate_loop']
