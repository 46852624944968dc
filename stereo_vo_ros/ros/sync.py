"""
Pair left and right images by their stamps, with bounded memory (pure Python, no rclpy).

Used by the node when ``message_filters`` is not importable. Stamps are integer nanoseconds so
that exact pairing compares integers, never floats.

Policy (``exact`` is ``approximate`` with a slop of zero):

* A new message is paired at once with the queued message of the other side whose stamp is
  nearest, if the difference is at most the slop (greedy: a better partner arriving later is
  not waited for; stereo cameras triggered together give equal stamps anyway).
* After a pair, every queued message not newer than the paired stamp of its side is dropped
  (it can no longer form a pair with increasing stamps) and counted as unmatched.
* A message not newer than the last paired stamp of its side is dropped as late.
* A stamp more than ``restart_jump_s`` before the newest stamp of its side means the input
  restarted (e.g. a looping bag): the queued messages of both sides are dropped (counted as
  unmatched), pairing starts afresh with this message and ``stats.restarts`` counts it.
* A second message with a stamp already queued on the same side replaces it (duplicate).
* A queued message older than the newest stamp of the other side minus the slop can no longer
  be paired (topics arrive in stamp order) and is dropped as unmatched; each side keeps at most
  ``queue_size`` messages, dropping the oldest.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field
import time
from typing import Any, Callable, Generic, TypeVar

T = TypeVar('T')

SIDES = ('left', 'right')


@dataclass(frozen=True)
class StereoPair(Generic[T]):
    """
    One synchronised pair.

    Attributes
    ----------
    stamp_ns : int
        Stamp of the left message (ns); the pair's stamp.
    right_stamp_ns : int
        Stamp of the right message (ns).
    left, right
        The paired items (e.g. Image messages).
    arrival_gap_s : float
        Time between the arrivals of the two items (s, the synchroniser's clock); 0 when
        unknown.

    """

    stamp_ns: int
    right_stamp_ns: int
    left: T
    right: T
    arrival_gap_s: float = 0.0


@dataclass
class SyncStats:
    """
    Counters of the synchroniser (all since construction or ``reset``).

    Attributes
    ----------
    pairs : int
        Pairs emitted.
    unmatched : dict
        Per side ('left', 'right'): messages dropped without a partner.
    late : dict
        Per side: messages dropped because they were not newer than the last pair.
    duplicates : dict
        Per side: messages that replaced a queued one with the same stamp.
    restarts : int
        Stamps that jumped back by more than the restart threshold (input restarted).

    """

    pairs: int = 0
    unmatched: dict = field(default_factory=lambda: dict.fromkeys(SIDES, 0))
    late: dict = field(default_factory=lambda: dict.fromkeys(SIDES, 0))
    duplicates: dict = field(default_factory=lambda: dict.fromkeys(SIDES, 0))
    restarts: int = 0

    @property
    def unsynchronized(self) -> int:
        """Messages of both sides that did not end up in a pair (unmatched + late)."""
        return sum(self.unmatched.values()) + sum(self.late.values())


class StereoSynchronizer(Generic[T]):
    """
    Pair two streams by stamp, exactly or approximately, in bounded memory.

    Parameters
    ----------
    mode : str
        ``exact`` (equal stamps) or ``approximate`` (stamps within ``slop_s``).
    slop_s : float
        Largest stamp difference of an approximate pair (s), >= 0; ignored when exact.
    queue_size : int
        Messages kept per side while waiting for a partner, >= 1.
    restart_jump_s : float
        A stamp this much (s) before the newest one of its side restarts the pairing, > 0.
    clock : callable
        Time of arrival of a message (s), for ``StereoPair.arrival_gap_s``.

    """

    def __init__(self, mode: str = 'approximate', slop_s: float = 0.005,
                 queue_size: int = 10, restart_jump_s: float = 1.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if mode not in ('exact', 'approximate'):
            raise ValueError(f"sync mode must be 'exact' or 'approximate', got {mode!r}")
        if not slop_s >= 0.0:
            raise ValueError(f'sync slop must be >= 0 s, got {slop_s!r}')
        if int(queue_size) < 1:
            raise ValueError(f'sync queue size must be >= 1, got {queue_size!r}')
        if not restart_jump_s > 0.0:
            raise ValueError(f'sync restart jump must be > 0 s, got {restart_jump_s!r}')
        self.mode = mode
        self.restart_ns = int(round(restart_jump_s * 1e9))
        self.slop_ns = 0 if mode == 'exact' else int(round(slop_s * 1e9))
        self.queue_size = int(queue_size)
        self.clock = clock
        self.reset()

    def reset(self) -> None:
        """Forget the queued messages, the last pair and the counters."""
        self._stamps: dict[str, list[int]] = {s: [] for s in SIDES}
        self._items: dict[str, list[tuple[Any, float]]] = {s: [] for s in SIDES}  # (item, arrival)
        self._last_paired: dict[str, int | None] = dict.fromkeys(SIDES)
        self._newest: dict[str, int | None] = dict.fromkeys(SIDES)
        self.stats = SyncStats()

    def queued(self, side: str) -> int:
        """Return the number of messages waiting on ``side`` ('left' or 'right')."""
        return len(self._stamps[side])

    def newest(self, side: str) -> int | None:
        """Return the newest stamp (ns) seen on ``side`` since the last (re)start, or None."""
        return self._newest[side]

    def add_left(self, stamp_ns: int, item: T) -> list[StereoPair[T]]:
        """Add a left message; return the pairs it completes (zero or one)."""
        return self.add('left', stamp_ns, item)

    def add_right(self, stamp_ns: int, item: T) -> list[StereoPair[T]]:
        """Add a right message; return the pairs it completes (zero or one)."""
        return self.add('right', stamp_ns, item)

    def add(self, side: str, stamp_ns: int, item: T) -> list[StereoPair[T]]:
        """
        Add a message of ``side`` with its stamp (ns) and return the completed pairs.

        Raises
        ------
        ValueError
            ``side`` is neither 'left' nor 'right'.

        """
        if side not in SIDES:
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        other = 'right' if side == 'left' else 'left'
        stamp_ns = int(stamp_ns)
        newest = self._newest[side]
        if newest is not None and stamp_ns < newest - self.restart_ns:
            self._restart()
        last = self._last_paired[side]
        if last is not None and stamp_ns <= last:
            self.stats.late[side] += 1
            return []
        stamps, items = self._stamps[side], self._items[side]
        entry = (item, self.clock())
        i = bisect.bisect_left(stamps, stamp_ns)
        if i < len(stamps) and stamps[i] == stamp_ns:
            items[i] = entry
            self.stats.duplicates[side] += 1
        else:
            stamps.insert(i, stamp_ns)
            items.insert(i, entry)
        if self._newest[side] is None or stamp_ns > self._newest[side]:
            self._newest[side] = stamp_ns

        j = self._nearest(other, stamp_ns)
        if j is not None:
            pair_items = {side: (stamp_ns, items[i]),
                          other: (self._stamps[other][j], self._items[other][j])}
            for s in SIDES:
                self._drop_until(s, pair_items[s][0])
                self._last_paired[s] = pair_items[s][0]
            self.stats.pairs += 1
            (ls, (li, lt)), (rs, (ri, rt)) = pair_items['left'], pair_items['right']
            return [StereoPair(ls, rs, li, ri, abs(lt - rt))]
        self._prune(side)
        self._prune(other)
        return []

    # -- internals ---------------------------------------------------------------------
    def _restart(self) -> None:
        """Start pairing afresh (stamps jumped back): queued messages count as unmatched."""
        for side in SIDES:
            self.stats.unmatched[side] += len(self._stamps[side])
            self._stamps[side].clear()
            self._items[side].clear()
            self._last_paired[side] = None
            self._newest[side] = None
        self.stats.restarts += 1

    def _nearest(self, side: str, stamp_ns: int) -> int | None:
        """Index of the queued message of ``side`` nearest to ``stamp_ns`` within the slop."""
        stamps = self._stamps[side]
        k = bisect.bisect_left(stamps, stamp_ns)
        best, best_d = None, None
        for idx in (k - 1, k):
            if 0 <= idx < len(stamps):
                d = abs(stamps[idx] - stamp_ns)
                if d <= self.slop_ns and (best_d is None or d < best_d):
                    best, best_d = idx, d
        return best

    def _drop_until(self, side: str, stamp_ns: int) -> None:
        """Remove queued messages of ``side`` with stamps <= ``stamp_ns``; count the others."""
        stamps = self._stamps[side]
        k = bisect.bisect_right(stamps, stamp_ns)
        dropped = k - (1 if k > 0 and stamps[k - 1] == stamp_ns else 0)
        self.stats.unmatched[side] += dropped
        del stamps[:k]
        del self._items[side][:k]

    def _prune(self, side: str) -> None:
        """Drop what can no longer be paired, then enforce the queue bound."""
        other = 'right' if side == 'left' else 'left'
        stamps = self._stamps[side]
        newest_other = self._newest[other]
        if newest_other is not None:
            k = bisect.bisect_left(stamps, newest_other - self.slop_ns)
            if k:
                self.stats.unmatched[side] += k
                del stamps[:k]
                del self._items[side][:k]
        excess = len(stamps) - self.queue_size
        if excess > 0:
            self.stats.unmatched[side] += excess
            del stamps[:excess]
            del self._items[side][:excess]
