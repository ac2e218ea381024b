"""Frame log of the bus (python-can ``Logger``: .asc, .blf, .log) and its replay.

For bug reports: set ``can.frame_log: /tmp/brace.blf`` and the master records every
frame it sees, both directions (the bus is opened with ``receive_own_messages``).
:func:`replay` plays such a file back onto a bus with python-can's ``LogReader`` and
``MessageSync`` (original timing, or as fast as possible); :class:`BusMonitor` decodes
the drives' frames of docs/can.md (TPDO1, heartbeat, EMCY) the way the master does, so
a replayed log gives the same positions, forces and faults as the live run.
"""
from __future__ import annotations

import struct
import threading
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import can

from .cia402 import State402, decode_state, emcy_description
from .pdo import TPDO1
from .units import AxisScaling

__all__ = ['open_frame_log', 'read_frames', 'replay', 'BusMonitor', 'DriveRecord']

SUFFIXES = ('.asc', '.blf', '.log')


def open_frame_log(path: str | Path) -> can.Listener:
    """A python-can writer for ``path`` (format from the suffix: .asc, .blf, .log).

    :raises ValueError: another suffix (named in the message).
    """
    p = Path(path)
    if p.suffix.lower() not in SUFFIXES:
        raise ValueError(f'can.frame_log {str(p)!r}: use one of {", ".join(SUFFIXES)}')
    p.parent.mkdir(parents=True, exist_ok=True)
    return can.Logger(str(p))


def read_frames(path: str | Path) -> Iterator[can.Message]:
    """The frames of a log file in order (python-can ``LogReader``)."""
    with can.LogReader(str(path)) as reader:
        yield from reader


def replay(path: str | Path, bus: can.BusABC, *, realtime: bool = True,
           skip: float = 60.0, stop: threading.Event | None = None) -> int:
    """Send the frames of a log onto ``bus``; returns how many were sent.

    :param realtime: keep the recorded timing (``MessageSync`` with timestamps), else
        send back to back.
    :param skip: longest silence kept (s), as ``MessageSync``'s ``skip``.
    """
    sent = 0
    with can.LogReader(str(path)) as reader:
        for msg in can.MessageSync(reader, timestamps=realtime, gap=0.0, skip=skip):
            if stop is not None and stop.is_set():
                break
            if msg.is_error_frame:
                continue        # a virtual bus cannot carry them faithfully; decode them with read_frames
            bus.send(can.Message(arbitration_id=msg.arbitration_id, data=msg.data,
                                 is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                                 dlc=msg.dlc))
            sent += 1
    return sent


@dataclass
class DriveRecord:
    """What a passive listener learned about one drive (SI)."""

    node_id: int
    statusword: int = 0
    position: float = float('nan')
    force: float = float('nan')
    tpdos: int = 0
    heartbeats: int = 0
    nmt: int | None = None
    emcy: list[tuple[int, str]] = field(default_factory=list)
    controlwords: int = 0
    target: float = float('nan')

    @property
    def state(self) -> State402:
        return decode_state(self.statusword)


class BusMonitor(can.Listener):
    """Passive decoder of the brace's frames (docs/can.md); no frame is ever sent.

    Feed it with a :class:`can.Notifier` on a bus, or call :meth:`feed` with frames
    (e.g. :func:`read_frames`).
    """

    def __init__(self, node_ids: Sequence[int], scaling: AxisScaling) -> None:
        self.scaling = scaling
        self.drives = {i: DriveRecord(i) for i in node_ids}
        self.syncs = 0
        self.frames = 0
        self.error_frames = 0
        self._lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        with self._lock:
            self.frames += 1
            if msg.is_error_frame:
                self.error_frames += 1
                return
            cob = msg.arbitration_id
            data = bytes(msg.data)
            if cob == 0x80 and not data:
                self.syncs += 1
                return
            fn, node = cob & 0x780, cob & 0x7F
            d = self.drives.get(node)
            if d is None:
                return
            if fn == 0x180 and len(data) >= TPDO1.size:
                sw, pos, load = TPDO1.unpack_from(data)
                d.statusword, d.position, d.force = sw, self.scaling.to_si(pos), self.scaling.force_to_si(load)
                d.tpdos += 1
            elif fn == 0x200 and len(data) >= 6:
                _, target = struct.unpack_from('<Hi', data)
                d.target = self.scaling.to_si(target)
                d.controlwords += 1
            elif fn == 0x700 and data:
                d.heartbeats += 1
                d.nmt = data[0] & 0x7F
            elif fn == 0x080 and len(data) >= 2:
                code = struct.unpack_from('<H', data)[0]
                d.emcy.append((code, emcy_description(code)))

    def feed(self, frames: Iterable[can.Message]) -> BusMonitor:
        for msg in frames:
            self.on_message_received(msg)
        return self

    def stop(self) -> None:
        pass


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m brace_control.can.framelog LOG [--replay --channel CH]``.

    Without ``--replay``: decode the log (SYNCs, per drive the last statusword, position,
    load-cell force and the EMCYs). With ``--replay``: play it onto a bus in real time.
    """
    import argparse

    from ..config import load_device_config
    from .units import scaling_from_config
    ap = argparse.ArgumentParser(prog='python -m brace_control.can.framelog', description=main.__doc__)
    ap.add_argument('log', help='.asc, .blf or .log file')
    ap.add_argument('--config', default='lumbar_brace', help='device YAML (scaling, node ids)')
    ap.add_argument('--replay', action='store_true', help='send the frames onto a bus')
    ap.add_argument('--interface', default='virtual')
    ap.add_argument('--channel', default='brace0')
    ap.add_argument('--fast', action='store_true', help='replay without the recorded timing')
    args = ap.parse_args(argv)
    cfg = load_device_config(args.config)
    if args.replay:
        with can.Bus(interface=args.interface, channel=args.channel) as bus:
            n = replay(args.log, bus, realtime=not args.fast)
        print(f'{n} frames replayed onto {args.interface}:{args.channel}')
        return 0
    node_ids = [int(i) for i in cfg.get_path('can.node_ids')]
    mon = BusMonitor(node_ids, scaling_from_config(cfg)).feed(read_frames(args.log))
    print(f'{mon.frames} frames, {mon.syncs} SYNC, {mon.error_frames} error frames')
    for node_id, d in mon.drives.items():
        emcy = ', '.join(f'{c:04X}h {t}' for c, t in d.emcy) or 'none'
        print(f'node {node_id}: {d.tpdos} TPDO1, last {d.state.value}, position {d.position:.6f} m, '
              f'force {d.force:.2f} N, NMT {d.nmt}; EMCY: {emcy}')
    return 0


if __name__ == '__main__':
    import sys
    sys.exit(main())
