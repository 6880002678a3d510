"""Scans waiting for their sensor pose: the policy of ``tf2_ros::MessageFilter``, without ROS.

A scan is inserted with the sensor pose at its own stamp, which tf may not know yet when the
scan arrives (the transform is published later, or the robot's localisation lags). ROS 2's
Python ``tf2_ros`` has no ``MessageFilter``, so the octolgp node keeps its scans in a
:class:`TfWaitQueue`: each waits until tf can give its pose, at most ``timeout`` seconds from
arrival, and at most ``queue_size`` wait at once (the oldest is dropped on overflow), as the
C++ filter's ``queue_size`` and ``buffer_timeout``. Unlike the C++ filter, scans leave in
arrival order: a scan whose pose is known waits for the ones before it to be posed or
dropped, because a map's newer evidence wins and the order of insertion is the map's.

The queue holds any objects and asks a ``ready`` callable whether each can be posed; times
are seconds on any one clock (the node's ROS clock, so simulated time works).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

from octolgp.errors import OctolgpError

__all__ = ["Drained", "TfWaitQueue"]

T = TypeVar("T")


@dataclass(frozen=True)
class Drained(Generic[T]):
    """What one :meth:`TfWaitQueue.drain` released.

    Attributes
    ----------
    ready : tuple
        Messages whose pose tf can give, in arrival order: insert them.
    timed_out : tuple
        Messages that waited longer than the timeout, in arrival order: skip them.
    """

    ready: tuple[T, ...]
    timed_out: tuple[T, ...]


class TfWaitQueue(Generic[T]):
    """Messages in arrival order, each waiting for its transform for at most ``timeout`` s.

    Parameters
    ----------
    queue_size : int
        The most messages waiting at once; pushing one more drops the oldest.
    timeout : float
        Seconds a message may wait for its transform (``>= 0``; 0 releases or drops it at
        the first :meth:`drain`).

    Raises
    ------
    OctolgpError
        On a ``queue_size`` below 1 or a negative or non-finite ``timeout``.
    """

    def __init__(self, queue_size: int, timeout: float) -> None:
        if isinstance(queue_size, bool) or not isinstance(queue_size, int) or queue_size < 1:
            raise OctolgpError(f"queue_size must be an integer >= 1, got {queue_size!r}")
        ok = isinstance(timeout, int | float) and not isinstance(timeout, bool)
        if not ok or not math.isfinite(timeout) or timeout < 0:
            raise OctolgpError(f"timeout must be a finite number >= 0 seconds, got {timeout!r}")
        self.queue_size = queue_size
        self.timeout = float(timeout)
        self._waiting: deque[tuple[float, T]] = deque()

    def __len__(self) -> int:
        return len(self._waiting)

    def push(self, msg: T, now: float) -> T | None:
        """Queue a message that arrived at ``now``; return the one dropped on overflow, if any."""
        self._waiting.append((float(now), msg))
        if len(self._waiting) > self.queue_size:
            return self._waiting.popleft()[1]
        return None

    def drain(self, ready: Callable[[T], bool], now: float) -> Drained[T]:
        """Release the head of the queue while its messages are posed or timed out.

        Parameters
        ----------
        ready : callable
            ``ready(msg)`` is True when tf can give the message's pose at its stamp.
        now : float
            The current time, seconds, on the clock of :meth:`push`.

        Returns
        -------
        Drained
            Stops at the first message that is neither ready nor past its timeout.
        """
        posed: list[T] = []
        dropped: list[T] = []
        while self._waiting:
            arrived, msg = self._waiting[0]
            if ready(msg):
                posed.append(msg)
            elif now - arrived >= self.timeout:
                dropped.append(msg)
            else:
                break
            self._waiting.popleft()
        return Drained(tuple(posed), tuple(dropped))
