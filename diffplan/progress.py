"""Progress bars that say "compiling" until the first result arrives, and time only what follows.

The first call of a jitted program compiles it (seconds here, minutes for an MJX program) before
anything runs. A plain tqdm bar counts that time as progress time, so its first rate and ETA
are wrong (an ETA of 7:25:07 on an evaluation of a minute). :class:`CompilingBar` reads
"compiling" until its first update, or until :meth:`CompilingBar.running` says the program
runs (a report from inside it), and measures its rate, so its ETA, from then on only: the
average since compilation ended, "?" until there is one. :meth:`CompilingBar.compiling` says
it again when another program compiles mid-bar. Every project bar is one (``bar(...)`` takes
tqdm's arguments).
"""
from __future__ import annotations

import time

from tqdm.std import tqdm

COMPILING = "compiling"


class CompilingBar(tqdm):
    """A tqdm bar whose postfix reads "compiling" until the program runs, and whose rate is
    the average since then (tqdm's own rate, while compiling, would count compile time)."""

    def __init__(self, *args, **kwargs):
        self._compiling, self._t0, self._n0 = True, None, 0
        super().__init__(*args, **kwargs)
        if not self.disable:
            self.set_postfix_str(COMPILING)

    def compiling(self, what: str = COMPILING) -> None:
        """Another program compiles: say ``what`` (and no ETA) until the next update."""
        self._compiling = True
        if not self.disable:
            self.set_postfix_str(what)

    def running(self, n: int | None = None) -> None:
        """The program runs: clear the note; the rate counts from now and from n units done
        (default the bar's count)."""
        if not self._compiling:
            return
        self._compiling = False
        self._t0, self._n0 = time.time(), self.n if n is None else n
        if not self.disable:
            self.set_postfix_str("")

    def update(self, n=1):
        if self._compiling:
            # The first update after compiling ends its phase; its own units took compile
            # time too, so they are not counted in the rate.
            self.running(self.n + n)
        return super().update(n)

    @property
    def format_dict(self):
        d = super().format_dict
        if not hasattr(self, "_compiling"):  # tqdm's own calls during __init__
            return d
        rate = 0.0  # falsy but not None: tqdm shows "?" and computes no rate of its own
        if not self._compiling and self._t0 is not None:
            elapsed = time.time() - self._t0
            done = self.n - self._n0
            if done > 0 and elapsed > 0:
                rate = done / elapsed
        d["rate"] = rate
        return d


def bar(*args, **kwargs) -> CompilingBar:
    """A :class:`CompilingBar` (tqdm's arguments)."""
    return CompilingBar(*args, **kwargs)
