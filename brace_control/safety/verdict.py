"""What a protective function answers for one sample (docs/safety.md, "Words used")."""
from __future__ import annotations

import enum
from dataclasses import dataclass

__all__ = ['Action', 'Verdict', 'OK']


class Action(enum.Enum):
    """The reaction a protective function asks for."""

    OK = 'ok'
    #: brake along the path and hold; the goal is aborted with the reason; nothing latches
    SOFT_STOP = 'soft stop'
    #: latch a protective stop until ``recover`` finds the cause gone
    PROTECTIVE_STOP = 'protective stop'


@dataclass(frozen=True)
class Verdict:
    """``action`` with its ``reason`` (empty for *ok*)."""

    action: Action
    reason: str = ''

    @property
    def ok(self) -> bool:
        return self.action is Action.OK


#: the answer when nothing is wrong
OK = Verdict(Action.OK)
