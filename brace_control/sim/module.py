"""A simulated CiA 401 analog-input module: the load cells wired to a node of their own.

Many labs wire the load cells not to the drives' analog inputs but to a separate CANopen I/O
module (CiA 401 "generic I/O modules": analog inputs 6401h:1..n, INTEGER16). With
``can.load_cell_node`` in the device YAML the master maps that module's TPDO on the same
SYNC as the drives'; with ``can.sim`` the simulated brace puts this module on the bus, its
inputs the actuators' load-cell readings (:class:`~brace_control.sim.brace.SimulatedBrace`).
"""
from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from pathlib import Path

from ..can.dictionary import STRUCT_CODES, ObjectRef
from ..can.units import LoadInput
from .device import SimulatedDevice

__all__ = ['SimulatedAnalogModule']


class SimulatedAnalogModule(SimulatedDevice):
    """A CiA 401 module whose analog inputs carry the load cells.

    :param node_id: its node id (``can.load_cell_node.node_id``).
    :param eds: its EDS (``can.load_cell_node.eds``).
    :param inputs: the objects wired to the actuators' load cells, in actuator order
        (``can.load_cell_node.objects``; 6401h:1..n by default).
    """

    def __init__(self, node_id: int, eds: str | Path, inputs: Sequence[ObjectRef], **kwargs) -> None:
        self.inputs = tuple(ObjectRef.parse(i) for i in inputs)
        #: the current reading of each input (counts of its data type), actuator order
        self.readings: list[int | float] = [0] * len(self.inputs)
        super().__init__(node_id, eds, **kwargs)
        self.load_inputs: list[LoadInput] = []
        for ref in self.inputs:
            var = self.dictionary.var(ref)
            if var is None or var.data_type not in STRUCT_CODES:
                raise ValueError(f'{self.dictionary.product} has no numeric object {ref} for a load cell')
            self.load_inputs.append(LoadInput.of(STRUCT_CODES[var.data_type]))
        self.readings[:] = [li.zero for li in self.load_inputs]     # the getters hold this list
        self._index = {(r.index, r.subindex): i for i, r in enumerate(self.inputs)}

    def _getter(self, index: int, sub: int) -> Callable[[], int]:
        i = self._index.get((index, sub))
        if i is not None:
            return functools.partial(self.readings.__getitem__, i)
        return super()._getter(index, sub)

    def _get(self, index: int, sub: int) -> int:
        i = self._index.get((index, sub))
        if i is not None:
            return self.readings[i]
        return super()._get(index, sub)
