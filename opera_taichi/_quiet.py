"""Silence chatter that C extensions print straight to the stdout/stderr file descriptors
(pybullet's build banner), so a `--quiet` run is quiet and stdout carries only our output."""
import contextlib
import ctypes
import os
import sys

try:
    _libc = ctypes.CDLL(None)
except OSError:  # not a POSIX libc: nothing buffered to flush
    _libc = None


@contextlib.contextmanager
def quiet_c_output():
    streams = []
    for stream in (sys.stdout, sys.stderr):
        try:
            streams.append((stream, stream.fileno()))
        except (AttributeError, OSError, ValueError):  # captured by pytest or an IDE: leave it
            pass
    saved = []
    try:
        with open(os.devnull, "w") as devnull:
            for stream, fd in streams:
                stream.flush()
                saved.append((fd, os.dup(fd)))
                os.dup2(devnull.fileno(), fd)
            yield
            if _libc is not None:
                _libc.fflush(None)  # C stdio buffers off a terminal: flush while still pointing at /dev/null
    finally:
        for fd, copy in saved:
            os.dup2(copy, fd)
            os.close(copy)
