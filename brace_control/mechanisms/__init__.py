"""Mechanism models: one module per mechanism, one shared protocol (:mod:`.base`).

>>> from brace_control.mechanisms import load_mechanism
>>> mech = load_mechanism('config/lumbar_brace.yaml')
"""
from .base import Mechanism, SingularPose, UnreachablePose
from .loader import MECHANISM_TYPES, load_mechanism, mechanism_from_config
from .continuum import Continuum2
from .fourbar import HoekenFourBar
from .rpr3 import Rpr3
from .rpr4 import Rpr4
from .rr2 import Rr2
from .rrr3 import Rrr3
from .spherical import Spherical3Rrr

__all__ = [
    'Mechanism', 'UnreachablePose', 'SingularPose', 'Rpr3', 'Rpr4', 'Rrr3', 'Rr2', 'HoekenFourBar',
    'Spherical3Rrr', 'Continuum2',
    'load_mechanism', 'mechanism_from_config', 'MECHANISM_TYPES',
]
