"""What every benchmark script checks in its options and says about the machine it ran on."""
from __future__ import annotations

import argparse
import os
import platform
import shlex
import sys


def at_least(least: float, kind=float, what: str = "a number"):
    """An argparse type: a number (int or float) >= least, refused in argparse's one line otherwise."""
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or not value >= least:
            raise argparse.ArgumentTypeError(f"expected {what} >= {least:g}, got {text!r}")
        return value
    return parse


def host_line() -> str:
    """The command as run and the machine: the CPU model, its logical CPUs and the Python."""
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            model = next((line.split(":", 1)[1].strip() for line in fh if line.startswith("model name")), model)
    except OSError:
        pass
    command = " ".join(shlex.quote(a) for a in [os.path.relpath(sys.argv[0])] + sys.argv[1:])
    return f"# python {command}\n# {model}, {os.cpu_count()} logical CPUs, Python {platform.python_version()}"
