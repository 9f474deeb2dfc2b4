"""A progress bar for long runs: simulated time, real-time factor and ETA, on a terminal only."""
from __future__ import annotations

import sys
from typing import TextIO

from tqdm import tqdm

# Redraw at most this often (wall seconds): the loop calls update() every rigid step.
REDRAW_INTERVAL = 0.2


class Progress:
    """`with Progress(duration) as bar: bar.update(sim_time, wall_time)`.

    Writes nothing at all when quiet=True or when the stream (stderr by default) is not a terminal,
    so logs and CI output stay clean.
    """

    def __init__(self, duration: float, *, quiet: bool = False, stream: TextIO | None = None):
        self.duration = float(duration)
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = not quiet and bool(getattr(self.stream, "isatty", lambda: False)())
        self._bar: tqdm | None = None
        self._last_draw = -float("inf")

    def __enter__(self) -> "Progress":
        if self.enabled:
            self._bar = tqdm(total=self.duration, file=self.stream, unit="s", dynamic_ncols=True,
                             bar_format="{l_bar}{bar}| {n:.2f}/{total:.2f} s simulated{postfix}",
                             mininterval=REDRAW_INTERVAL, leave=True)
        return self

    def update(self, sim_time: float, wall_time: float) -> None:
        """sim_time: simulated seconds done; wall_time: wall seconds since the run started."""
        if self._bar is None:
            return
        done = sim_time >= self.duration
        if wall_time - self._last_draw < REDRAW_INTERVAL and not done:
            return
        self._last_draw = wall_time
        self._bar.n = min(max(sim_time, 0.0), self.duration)
        self._bar.set_postfix_str(self.describe(sim_time, wall_time), refresh=False)
        self._bar.refresh()

    def describe(self, sim_time: float, wall_time: float) -> str:
        """'RTF 0.52x, ETA 00:12': real-time factor (simulated / wall seconds) and time left at that pace."""
        if sim_time <= 0 or wall_time <= 0:
            return "RTF ?, ETA ?"
        rtf = sim_time / wall_time
        left = max(self.duration - sim_time, 0.0) / rtf
        return f"RTF {rtf:.3g}x, ETA {tqdm.format_interval(left)}"

    def __exit__(self, *exc) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
