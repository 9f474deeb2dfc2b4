"""`--pace realtime`: simulated time kept to the wall clock (the default with a ROS bridge), by an observer that sleeps.

It is the one observer whose job is to slow the loop. The pace is anchored after the first step (kernel compilation
is not lag). When the simulation cannot keep up (two 2-second wall windows in a row below 0.9x real time) it says so
once with the real-time factor, and runs on as fast as it can without racing to catch up later; the run's real-time
factor is in manifest.json and said again when the run ends.
"""
from __future__ import annotations

import sys
import time

from .observers import Observer

WINDOW = 2.0          # wall seconds per real-time-factor window
SLOW = 0.9            # below this factor a window is slow
MAX_LAG = 0.25        # wall seconds behind the pace after which the anchor moves (no catching up in bursts)


class RealTimePacer(Observer):
    rate = 200.0      # Hz of simulated time: sleeps in 5 ms pieces

    def __init__(self, quiet: bool = False):
        self.quiet = quiet

    @property
    def key(self) -> str:
        return "RealTimePacer"

    def start(self, sim, run) -> None:
        self._anchor = None
        self._window = None
        self._slow_windows = 0
        self.said = False
        self._first = None

    def sample(self, sim) -> None:
        now = time.perf_counter()
        if sim.step_count == 0:
            return
        if self._anchor is None:
            self._anchor = self._window = self._first = (sim.t, now)
            return
        t0, w0 = self._anchor
        ahead = (w0 + (sim.t - t0)) - now
        if ahead > 0:
            time.sleep(ahead)
            now += ahead
        elif -ahead > MAX_LAG:
            self._anchor = (sim.t, now)
        ts, ws = self._window
        if now - ws >= WINDOW:
            rtf = (sim.t - ts) / (now - ws)
            self._slow_windows = self._slow_windows + 1 if rtf < SLOW else 0
            self._window = (sim.t, now)
            if self._slow_windows >= 2 and not self.said:
                self.said = True  # (said through the simulation: the manifest's run_warnings keep it)
                sim._warn(f"--pace realtime: the simulation cannot keep up with the wall clock here (real-time "
                          f"factor {rtf:.2f}); it runs as fast as it can, and /clock runs slower than real time")

    def close(self, sim, status, message) -> None:
        if self.said and self._first is not None and not self.quiet:
            t0, w0 = self._first
            wall = time.perf_counter() - w0
            if wall > 0:
                print(f"--pace realtime: real-time factor {(sim.t - t0) / wall:.2f} over the run", file=sys.stderr)
