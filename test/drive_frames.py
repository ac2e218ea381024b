"""A CANopen master's side of simulated drives, frame by frame: no bus, no threads.

Shared by test_sim_drive.py and test_sim_brace.py. :class:`FrameMaster` calls the drives'
own entry points (:meth:`SimulatedDrive.on_frame`, :meth:`SimulatedDrive.on_sync`) with
the frames a CiA 402 master would put on the bus, and collects what they send. The
frame layouts are written out here from CiA 301 (NMT, expedited SDO download) and
docs/can.md (RPDO1, RPDO2, TPDO1), not taken from the simulator.
"""
from __future__ import annotations

import struct
from collections.abc import Callable, Iterable, Sequence

from brace_control.sim.drive import SimulatedDrive


class FrameMaster:
    """Drive ``drives`` by frames; simulated time advances only with :meth:`sync`.

    :param drives: simulated drives, not yet powered on; this object becomes their bus.
    """

    def __init__(self, drives: Sequence[SimulatedDrive]) -> None:
        self.drives = list(drives)
        self.t = 0.0
        self.received: list[tuple[int, bytes]] = []
        for d in self.drives:
            d.attach(self._on_tx)
            d.power_on()

    def _on_tx(self, cob_id: int, data: bytes) -> None:
        self.received.append((cob_id, bytes(data)))

    def send(self, cob_id: int, data: bytes) -> None:
        """One frame to every drive (a bus delivers it to all)."""
        for d in self.drives:
            d.on_frame(cob_id, data, self.t)

    def sync(self, dt: float) -> None:
        """SYNC after ``dt`` seconds (the drives move over ``dt``, answer, latch RPDOs)."""
        self.t += dt
        for d in self.drives:
            d.on_sync(dt)

    def nmt_start(self) -> None:
        """NMT start remote node, all nodes (CiA 301: 0x000, ``01 00``)."""
        self.send(0x000, b'\x01\x00')

    def sdo_write(self, node_id: int, index: int, sub: int, fmt: str, value: int) -> None:
        """Expedited SDO download (CiA 301 §7.2.4.3.3): asserts the server's confirmation."""
        raw = struct.pack('<' + fmt, value)
        cmd = 0x23 | ((4 - len(raw)) << 2)
        mark = len(self.received)
        self.send(0x600 + node_id, struct.pack('<BHB', cmd, index, sub) + raw.ljust(4, b'\0'))
        replies = [d for c, d in self.received[mark:] if c == 0x580 + node_id]
        assert replies and replies[0][0] == 0x60, \
            f'SDO {index:04X}h:{sub} = {value} to node {node_id}: {replies[0].hex() if replies else "no reply"}'

    def rpdo1(self, node_id: int, controlword: int, target_counts: int) -> None:
        """RPDO1 (0x200 + id): 6040h U16 + 607Ah I32."""
        self.send(0x200 + node_id, struct.pack('<Hi', controlword, target_counts))

    def rpdo2(self, node_id: int, velocity_offset_counts_s: int) -> None:
        """RPDO2 (0x300 + id): 60B1h I32, counts/s."""
        self.send(0x300 + node_id, struct.pack('<i', velocity_offset_counts_s))

    def tpdo1(self, node_id: int) -> tuple[int, int, int]:
        """The last TPDO1 (0x180 + id): statusword, position actual (counts), 2401h."""
        for cob, data in reversed(self.received):
            if cob == 0x180 + node_id:
                return struct.unpack('<Hih', data)
        raise AssertionError(f'no TPDO1 from node {node_id}')

    def emcy_codes(self, node_id: int) -> list[int]:
        """Error codes of the EMCYs node ``node_id`` sent (0x080 + id)."""
        return [struct.unpack_from('<H', d)[0] for c, d in self.received if c == 0x80 + node_id]

    def enable_csp(self, home_counts: Sequence[int], *,
                   configure: Callable[[int], Iterable[tuple[int, int, str, int]]] | None = None
                   ) -> list[int]:
        """Boot to CSP in OPERATION ENABLED, homed (method 35: 6064h := 607Ch).

        :param home_counts: 607Ch per drive (the counts its present length is to read).
        :param configure: ``configure(node_id)`` gives extra SDO writes ``(index, sub,
            fmt, value)`` for that drive before NMT start (e.g. the PDO mapping).
        :returns: each drive's position actual after enabling (counts).
        """
        for d, home in zip(self.drives, home_counts):
            nid = d.node_id
            for index, sub, fmt, value in (configure(nid) if configure else ()):
                self.sdo_write(nid, index, sub, fmt, value)
            self.sdo_write(nid, 0x607C, 0, 'i', home)
            self.sdo_write(nid, 0x6098, 0, 'b', 35)
            self.sdo_write(nid, 0x6060, 0, 'b', 6)              # homing
            for cw in (0x06, 0x07, 0x0F, 0x1F, 0x0F):           # CiA 402: 2, 3, 4; bit 4 homes
                self.sdo_write(nid, 0x6040, 0, 'H', cw)
            self.sdo_write(nid, 0x6060, 0, 'b', 8)              # cyclic synchronous position
        self.nmt_start()
        self.sync(0.002)
        out = []
        for d in self.drives:
            sw, pos, _ = self.tpdo1(d.node_id)
            assert sw & 0x6F == 0x27, f'node {d.node_id}: OPERATION ENABLED expected, sw={sw:#06x}'
            out.append(pos)
        return out
