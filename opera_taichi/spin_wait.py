"""Keep the other CPU cores running while the soil steps (`sim.spin_wait`).

Taichi's CPU thread pool puts its threads to sleep after each parallel loop, and a soil substep runs three of them.
On a virtual machine whose idle vCPU halts at once (the 2-vCPU cloud VM of docs/performance.md), a thread woken
there starts 0.1-0.3 ms late, which is as long as a loop's work in a dig at 5 cm. A helper process per
other core, at the lowest priority, spins while the simulation steps and for SPIN_FOR after its last step, so the
vCPU is running when Taichi's thread wakes; anything else that wants the core preempts it. OpenMP runtimes wait for
work the same way (KMP_BLOCKTIME). The helpers only burn time: results do not depend on them. `auto`, the
scenes' default, starts them only where idle CPUs halt at once (idle_cpus_halt_at_once).
"""
from __future__ import annotations

import atexit
import mmap
import os
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SPIN_FOR = 0.2  # s a helper spins after the last step before it sleeps (OpenMP's KMP_BLOCKTIME default)
_DEADLINE = struct.Struct("d")  # time.monotonic() up to which the helpers spin, in a shared page

# The helper: spins while the shared deadline is ahead, else sleeps in 5 ms naps; leaves when its parent has gone.
_HELPER = r"""
import mmap, os, struct, sys, time
fd, parent = int(sys.argv[1]), int(sys.argv[2])
os.nice(19)
page = mmap.mmap(fd, 8)
deadline = struct.Struct("d")
while os.getppid() == parent:
    while time.monotonic() < deadline.unpack_from(page)[0]:
        for _ in range(10000):
            pass
    time.sleep(0.005)
"""


class SpinWait:
    """The helpers of one process: `touch()` after each step keeps them spinning for SPIN_FOR; `close()` ends them."""

    def __init__(self, helpers: int):
        self._file = tempfile.TemporaryFile()
        self._file.write(b"\0" * _DEADLINE.size)
        self._file.flush()
        self._page = mmap.mmap(self._file.fileno(), _DEADLINE.size)
        fd = self._file.fileno()
        # (no standard streams: a helper must not hold open a pipe that a caller reads the run's output from)
        self.processes = [subprocess.Popen([sys.executable, "-c", _HELPER, str(fd), str(os.getpid())],
                                           pass_fds=(fd,), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                           stderr=subprocess.DEVNULL)
                          for _ in range(helpers)]

    def touch(self) -> None:
        _DEADLINE.pack_into(self._page, 0, time.monotonic() + SPIN_FOR)

    def close(self) -> None:
        _DEADLINE.pack_into(self._page, 0, 0.0)
        for p in self.processes:
            p.kill()
            p.wait()
        self.processes = []
        self._page.close()
        self._file.close()


_shared: SpinWait | None = None


def idle_cpus_halt_at_once(sys_root: str | Path = "/sys") -> bool:
    """Whether an idle CPU here halts without polling first: a VM guest whose cpuidle driver is `haltpoll` with
    `guest_halt_poll_ns` 0 (the Firecracker VM of docs/performance.md), where a woken thread starts 0.1-0.3 ms late.
    With polling on (the driver's default, 200 us) or on bare metal, a thread woken between two loops finds its CPU
    still running or in a shallow state: the helpers would only burn time there."""
    root = Path(sys_root)
    try:
        driver = (root / "devices/system/cpu/cpuidle/current_driver").read_text().strip()
        poll_ns = int((root / "module/haltpoll/parameters/guest_halt_poll_ns").read_text())
    except (OSError, ValueError):
        return False
    return driver == "haltpoll" and poll_ns == 0


def wanted(setting: bool | str) -> bool:
    """sim.spin_wait's true / false, or auto: on where idle CPUs halt at once."""
    return idle_cpus_halt_at_once() if setting == "auto" else bool(setting)


def helpers_wanted(threads: int) -> int:
    """One helper per other core that Taichi's threads may run on."""
    return max(0, min(threads, os.cpu_count() or 1) - 1)


def spin_wait(threads: int) -> SpinWait | None:
    """The process's helpers (started on first use and kept for the process: Taichi's pool is per process too);
    None where there is no other core."""
    global _shared
    if _shared is None and helpers_wanted(threads) > 0:
        _shared = SpinWait(helpers_wanted(threads))
        atexit.register(_shared.close)
    return _shared
