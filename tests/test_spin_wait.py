"""sim.spin_wait: helper processes keep the other cores running while a simulation steps.

- a run with it gives the same bits as one without, and its manifest says how many helpers ran;
- `auto` turns it on exactly where idle CPUs halt at once (the haltpoll cpuidle driver with polling off);
- a helper spins only while it is touched, naps after SPIN_FOR, and leaves when its parent dies, even by SIGKILL.
"""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from opera_taichi import spin_wait

ROOT = Path(__file__).resolve().parent.parent
BLADE = str(ROOT / "scenes" / "blade_cut.yaml")
SHORT_BLADE = ["--quiet", "--set", "soil.overrides.radius=0.04", "--set", "sim.duration=0.4", "--set",
               "output.plots=false", "--set", "tools.0.start.2=0.2"]
WAIT = 20.0  # s: the most a state change below may take on a busy machine (each takes milliseconds)


def _state(pid: int) -> str | None:
    """The process's scheduler state (R running, S sleeping, ...), None once it is gone or a zombie."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None if state in ("Z", "X") else state


def _until(condition, what: str) -> None:
    deadline = time.monotonic() + WAIT
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.01)


def _helpers_of(parent: int) -> list[int]:
    """Helper processes started by `parent` (their command line ends with its pid)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                args = (entry / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"-c" in args and len(args) >= 3 and args[-2] == str(parent).encode() and _state(int(entry.name)):
                found.append(int(entry.name))
    return found


pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists() or (os.cpu_count() or 1) < 2,
                                reason="needs Linux's /proc and a second core")


def test_a_run_with_spin_wait_gives_the_same_bits_and_leaves_no_helper_behind(tmp_path):
    outs = {}
    for flag in ("false", "true", "auto"):
        out = tmp_path / flag
        proc = subprocess.Popen([sys.executable, str(ROOT / "cli.py"), "run", BLADE, "--out", str(out),
                                 *SHORT_BLADE, "--set", f"sim.spin_wait={flag}"], cwd=ROOT)
        assert proc.wait() == 0
        assert _helpers_of(proc.pid) == []  # closed at exit, not left spinning
        outs[flag] = out
    helpers = {flag: json.loads((out / "manifest.json").read_text())["spin_wait_helpers"] for flag, out in outs.items()}
    wanted = spin_wait.helpers_wanted(json.loads((outs["true"] / "manifest.json").read_text())["cpu_threads"])
    assert helpers == {"false": 0, "true": wanted, "auto": wanted if spin_wait.idle_cpus_halt_at_once() else 0}
    assert helpers["true"] >= 1
    wrenches = {(out / "tool_wrench.csv").read_bytes() for out in outs.values()}
    assert len(wrenches) == 1


def _sysfs(root: Path, driver: str | None, poll_ns: str | None) -> Path:
    if driver is not None:
        (root / "devices/system/cpu/cpuidle").mkdir(parents=True)
        (root / "devices/system/cpu/cpuidle/current_driver").write_text(driver + "\n")
    if poll_ns is not None:
        (root / "module/haltpoll/parameters").mkdir(parents=True)
        (root / "module/haltpoll/parameters/guest_halt_poll_ns").write_text(poll_ns + "\n")
    return root


@pytest.mark.parametrize("driver, poll_ns, halts", [
    ("haltpoll", "0", True),             # the Firecracker VM measured: auto turns the helpers on
    ("haltpoll", "200000", False),       # the driver's default: it polls 200 us before it halts
    ("intel_idle", None, False),         # bare metal
    (None, None, False),                 # no cpuidle at all (a container without /sys, another OS)
    ("haltpoll", None, False),           # the driver's parameters unreadable: not assumed
    ("haltpoll", "garbage", False),
])
def test_auto_spins_only_where_idle_cpus_halt_at_once(tmp_path, driver, poll_ns, halts):
    assert spin_wait.idle_cpus_halt_at_once(_sysfs(tmp_path, driver, poll_ns)) is halts


def _always(pid: int, state: str) -> bool:
    """The helper is in `state` at each of 20 looks over about 40 ms."""
    for _ in range(20):
        if _state(pid) != state:
            return False
        time.sleep(0.002)
    return True


def test_a_helper_spins_while_touched_naps_after_and_leaves_when_its_parent_is_killed():
    # (SPIN_FOR raised to 3 s in the parent, so the looks below fall inside the spin on a busy machine too)
    parent = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom opera_taichi import spin_wait\nspin_wait.SPIN_FOR = 3.0\n"
         "helpers = spin_wait.SpinWait(1)\nprint(helpers.processes[0].pid, flush=True)\nfor line in sys.stdin:\n"
         "    helpers.touch()\n    print('touched', flush=True)\n"],
        cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        helper = int(parent.stdout.readline())
        _until(lambda: _helpers_of(parent.pid) == [helper], "the helper runs as its parent's child")
        _until(lambda: _always(helper, "S"), "an untouched helper naps")
        parent.stdin.write("touch\n")
        parent.stdin.flush()
        assert parent.stdout.readline().strip() == "touched"
        _until(lambda: _state(helper) == "R", "a touched helper wakes from its nap")
        assert _always(helper, "R"), "a touched helper spins"
        _until(lambda: _always(helper, "S"), "a helper naps again after SPIN_FOR")
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        _until(lambda: _state(helper) is None, "a helper leaves when its parent is gone")
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()


def test_spin_wait_is_yes_no_or_auto(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "cli.py"), "run", BLADE, "--out", str(tmp_path / "bad"),
                           *SHORT_BLADE, "--set", "sim.spin_wait=2"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 2
    assert "sim.spin_wait" in proc.stderr and "true, false or auto" in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
