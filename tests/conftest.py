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
