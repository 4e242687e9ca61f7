"""Progress bars that move while one jitted call runs a whole evaluation.

``RELAY`` is the host function handed to ``diffplan.StreamRollout(on_move=...)``: the jitted
pool reports its number of retired episodes after every move through ``jax.debug.callback``,
with an integer token naming the bar. The relay is one fixed object, so the compiled function
is reused from one evaluation to the next; bars are registered per evaluation with
:meth:`Relay.attach` and detached when it ends (the only mutable state: which bars are open).
A report means the program runs: a ``diffplan.progress.CompilingBar`` (``bar``) stops saying
"compiling" at the first one and times its ETA from there.
"""
from __future__ import annotations

import itertools
import threading

from diffplan.progress import CompilingBar, bar

__all__ = ["PARTS", "RELAY", "Relay", "CompilingBar", "bar"]


PARTS = 64
"""Reports of part p (e.g. a device's slice of the episodes) of token t arrive as
t * PARTS + p; the bar shows the sum over parts."""


class Relay:
    """Routes (token, count) reports to open tqdm bars: bar.n = offset + the sum of the latest
    count of each part."""

    def __init__(self):
        self._bars = {}
        self._tokens = itertools.count(1)
        self._lock = threading.Lock()

    def attach(self, bar, offset: int = 0) -> int:
        """Registers a bar; returns its token (send reports as token * PARTS + part)."""
        with self._lock:
            token = next(self._tokens) % (2 ** 31 // PARTS - 1)
            self._bars[token] = (bar, offset, {})
        return token

    def detach(self, token: int) -> None:
        with self._lock:
            self._bars.pop(int(token), None)

    def __call__(self, token_part, count) -> None:
        token, part = divmod(int(token_part), PARTS)
        with self._lock:
            entry = self._bars.get(token)
            if entry is None:
                return
            bar, offset, counts = entry
            counts[part] = max(counts.get(part, 0), int(count))
            value = offset + sum(counts.values())
        if isinstance(bar, CompilingBar):
            bar.running()
        if value > bar.n:
            bar.update(value - bar.n)

    def __hash__(self):
        return id(self)

    def __eq__(self, other):
        return other is self


RELAY = Relay()
