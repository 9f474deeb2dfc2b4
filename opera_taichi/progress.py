"""A progress display for long runs, on a terminal only: the set-up phases (the bed settling, with its own
bar; the kernels compiling), then simulated time, real-time factor and ETA, ending at 100 %."""
from __future__ import annotations

import sys
from typing import TextIO

from tqdm import tqdm

# Redraw at most this often (wall seconds): the loop calls update() every few rigid steps.
REDRAW_INTERVAL = 0.2


class Progress:
    """`with Progress(duration) as bar: bar.phase(...); bar.begin_run(t0); bar.update(sim_time, wall_time)`.

    Writes nothing at all when quiet=True or when the stream (stderr by default) is not a terminal,
    so logs and CI output stay clean.
    """

    def __init__(self, duration: float, *, quiet: bool = False, stream: TextIO | None = None):
        self.duration = float(duration)
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = not quiet and bool(getattr(self.stream, "isatty", lambda: False)())
        self._bar: tqdm | None = None
        self._phase: tqdm | None = None
        self._last_draw = -float("inf")

    def __enter__(self) -> "Progress":
        return self

    # ------------------------------------------------------------------------------------------ set-up phases
    def phase(self, text: str) -> None:
        """A set-up phase without a measure of its own: its name and the wall time it has taken."""
        if not self.enabled:
            return
        self._end_phase()
        self._phase = tqdm(total=None, file=self.stream, bar_format="{desc}: {elapsed}", desc=text, leave=False,
                           mininterval=REDRAW_INTERVAL)
        self._phase.refresh()

    def settling(self, simulated: float, budget: float) -> None:
        """The soil bed settling: simulated seconds done of at most `budget` (it stops early once at rest)."""
        if not self.enabled:
            return
        if self._phase is None or self._phase.total is None:
            self._end_phase()
            self._phase = tqdm(total=budget, file=self.stream, unit="s", desc="settling the soil bed (cached after)",
                               bar_format="{desc}: {bar}| {n:.2f}/{total:.2f} s simulated, {elapsed}", leave=False,
                               mininterval=REDRAW_INTERVAL)
        self._phase.n = min(simulated, budget)
        self._phase.refresh()

    def _end_phase(self) -> None:
        if self._phase is not None:
            self._phase.close()
            self._phase = None

    # ------------------------------------------------------------------------------------------ the run
    def begin_run(self, sim_time: float) -> None:
        if not self.enabled:
            return
        self._end_phase()
        self._bar = tqdm(total=self.duration, file=self.stream, unit="s", dynamic_ncols=True, initial=sim_time,
                         bar_format="{l_bar}{bar}| {n:.2f}/{total:.2f} s simulated{postfix}",
                         mininterval=REDRAW_INTERVAL, leave=True)

    def update(self, sim_time: float, wall_time: float, start: float = 0.0, final: bool = False) -> None:
        """sim_time: simulated seconds done; wall_time: wall seconds since simulated time `start`."""
        if self._bar is None:
            return
        if wall_time - self._last_draw < REDRAW_INTERVAL and not final:
            return
        self._last_draw = wall_time
        self._bar.n = min(max(sim_time, 0.0), self.duration)
        self._bar.set_postfix_str(self.describe(sim_time, wall_time, start), refresh=False)
        self._bar.refresh()

    def describe(self, sim_time: float, wall_time: float, start: float = 0.0) -> str:
        """'RTF 0.52x, ETA 00:12': real-time factor (simulated / wall seconds) and time left at that pace."""
        if sim_time <= start or wall_time <= 0:
            return "RTF ?, ETA ?"
        rtf = (sim_time - start) / wall_time
        left = max(self.duration - sim_time, 0.0) / rtf
        return f"RTF {rtf:.3g}x, ETA {tqdm.format_interval(left)}"

    def __exit__(self, *exc) -> None:
        self._end_phase()
        if self._bar is not None:
            self._bar.close()
            self._bar = None
