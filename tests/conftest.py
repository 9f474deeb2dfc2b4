"""Set-up shared by every test file."""
import os
from pathlib import Path

# The two pytest-xdist workers compile the same kernels at the same moment. With one shared Taichi offline cache,
# a cold cache once gave a worker a kernel that did not match its signature ("RuntimeError: argument not found"
# launching gather_particles; the same test passed on the warm cache), most likely a cache entry read while the
# other worker wrote it. Each worker gets its own cache directory.
_worker = os.environ.get("PYTEST_XDIST_WORKER")
if _worker and "TI_OFFLINE_CACHE_FILE_PATH" not in os.environ:
    os.environ["TI_OFFLINE_CACHE_FILE_PATH"] = str(Path.home() / ".cache" / "taichi" / f"ticache-{_worker}")

# Third-party inputs (OPERA's URDF, Unity's ROS-TCP-Endpoint, com3_msgs) live in ../shared beside the checkout, as
# on CI; OPERA_TAICHI_SHARED names another place.
SHARED = Path(os.environ.get("OPERA_TAICHI_SHARED") or Path(__file__).resolve().parents[2] / "shared")
# On CI every test runs: a missing third-party input or program is a failure there, not a skip.
ON_CI = os.environ.get("CI") == "true"


def kill_after_first_checkpoint(proc, run_dir: Path, timeout: float = 600.0) -> None:
    """SIGKILL a `run --checkpoint-every` process as soon as its first checkpoint is on disk (it may have gone on a
    little: the stretch a resume simulates again)."""
    import signal
    import time

    deadline = time.monotonic() + timeout
    try:
        while not list((Path(run_dir) / "checkpoints").glob("step-*.ckpt.npz")):
            assert proc.poll() is None, "the run ended before its first checkpoint"
            assert time.monotonic() < deadline
            time.sleep(0.02)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert proc.returncode == -signal.SIGKILL


def a_file_a_run_folder_and(tmp_path: Path, name: str, meta: str, text: str) -> tuple[list, Path]:
    """(out, what the refusal says) for an --out that is a file, a run folder, and a folder holding `meta` with
    `text` (another study's or calibration's)."""
    afile = tmp_path / "a.csv"
    afile.write_text("t\n")
    run = tmp_path / "run"
    run.mkdir()
    (run / "manifest.json").write_text('{"status": "done", "scene": {}}')
    other = tmp_path / name
    other.mkdir()
    (other / meta).write_text(text)
    return [(afile, "is a file, not a folder"), (run, f"is the run folder {run}"),
            (run / "sub", f"lies inside the run folder {run}")], other
