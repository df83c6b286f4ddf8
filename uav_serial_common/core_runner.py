"""Drive a device core without I/O: step it, carry out its actions in order, feed results back.

A core (issue 22: a device's rules as a state machine with no thread, lock, clock or port) takes
one event at a time and returns the actions to carry out. `run_core` is the loop around it: each
action goes, in the order the core gave, to the handler of its type, and the events a handler
gives back (the reply to a frame it sent, or that the reply did not come, or that the link went
down) are stepped in turn, after the actions before them. The handlers do the I/O (a link, the
black box, a device model in virtual time); the runner knows nothing of any device.
"""

from __future__ import annotations

from collections import deque
from typing import Any, Callable, Dict, Iterable, List, Optional, Protocol, Type


class Core(Protocol):
    """What `run_core` drives: one event in, the actions to carry out out."""

    def step(self, event: Any) -> List[Any]:
        """Take one event; return the actions, in order."""


Handler = Callable[[Any], Optional[Iterable[Any]]]
"""Carries out one action; returns the events it brought about (or None)."""

MAX_STEPS = 10_000
"""A core that never stops asking is a bug: the runner stops it loudly."""


def run_core(core: Core, events: Iterable[Any], handlers: Dict[Type, Handler],
             max_steps: int = MAX_STEPS) -> List[Any]:
    """Step `core` with `events` and with every event the handlers give back, until none is left.

    Each action is carried out by ``handlers[type(action)]`` (an action of a type with no
    handler is a TypeError: a core's request is never dropped unseen). Returns every action
    carried out, in order (the caller finds its answer there).
    """
    queue = deque(events)
    done: List[Any] = []
    steps = 0
    while queue:
        steps += 1
        if steps > max_steps:
            raise RuntimeError(f'the core took {max_steps} events without settling')
        for action in core.step(queue.popleft()):
            handler = handlers.get(type(action))
            if handler is None:
                raise TypeError(f'no handler for the action {type(action).__name__}')
            done.append(action)
            queue.extend(handler(action) or ())
    return done
