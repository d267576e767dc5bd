"""The frames of a clip as a moving time window needs them: each made once, prepared once, released behind.

The ``denoise`` command reads frames from files and the progressive loop renders them; both then filter
every query time from the frames of its window (:func:`torchmanifold.timewindow.window`), and
neighbouring windows share frames. :class:`SlidingFrames` holds that bookkeeping for both, so memory is
bounded by the window whatever the clip's length.
"""
from __future__ import annotations

from typing import Callable, Generic, Mapping, Sequence, TypeVar

__all__ = ["SlidingFrames"]

F = TypeVar("F")  # a frame as made (read from a file, rendered)
P = TypeVar("P")  # what is derived from one frame alone (a FrameState)


class SlidingFrames(Generic[F, P]):
    """Frames ``k`` of a clip for windows that only move on (each starts at or after the one before).

    Args:
        make: ``make(k)`` makes frame ``k`` (reads or renders it), the first time a window holds it.
        prepare: ``prepare(k, frame)`` derives what the filter needs from that frame alone, once.
        made: frames made already (e.g. the first, read to learn the clip's layout).

    Frames before the start of the latest window are released with what was prepared from them.

    Attributes:
        served: frames handed out so far, each counted once.
    """

    def __init__(self, make: Callable[[int], F], prepare: Callable[[int, F], P],
                 made: Mapping[int, F] | None = None):
        self._make, self._prepare = make, prepare
        self._frames: dict[int, F] = dict(made or {})
        self._prepared: dict[int, P] = {}
        self._served: set[int] = set()
        self.served = 0

    def frames(self, ids: Sequence[int]) -> list[F]:
        """The frames ``ids`` (increasing); frames before ``ids[0]`` are released."""
        for k in ids:
            if k not in self._frames:
                self._frames[k] = self._make(k)
            if k not in self._served:
                self._served.add(k)
                self.served += 1
        for k in [k for k in self._frames if k < ids[0]]:
            del self._frames[k]
            self._prepared.pop(k, None)
        return [self._frames[k] for k in ids]

    def prepared(self, ids: Sequence[int]) -> list[P]:
        """``prepare`` of the frames ``ids`` (increasing), each computed once."""
        for k, frame in zip(ids, self.frames(ids)):
            if k not in self._prepared:
                self._prepared[k] = self._prepare(k, frame)
        return [self._prepared[k] for k in ids]

    def forget_prepared(self) -> None:
        """Drop what was prepared (the next :meth:`prepared` derives it afresh, e.g. for new settings)."""
        self._prepared = {}
