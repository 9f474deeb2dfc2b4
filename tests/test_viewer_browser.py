"""The 3-D view in a real browser: Debian's chromium, headless, software WebGL, driven over the DevTools protocol
(cdp_browser.py). Each test polls screenshots until the machine (its orange) and the soil (the height colour map)
each cover a minimum number of pixels (the view fades in), then until the machine's pixels move. Screenshots are
kept in a folder the tests print (and copied to $OPERA_TAICHI_SHOTS when set). Without chromium the tests skip,
unless CI is "true"."""
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("viser")
pytest.importorskip("websocket")

from cdp_browser import Browser, chromium_or_skip  # noqa: E402

from opera_taichi import cli  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "scenes" / "zx120_excavation.yaml"
COARSE = ["--set", "soil.overrides.radius=0.12", "--set", "output.plots=false"]
WIDTH, HEIGHT = 1280, 800
MIN_MACHINE, MIN_SOIL, MIN_MOVED = 5000, 2000, 800   # pixels at 1280 x 800


# ---------------------------------------------------------------------------------------------- pixels
def _viridis() -> np.ndarray:
    from matplotlib import colormaps

    return (colormaps["viridis"](np.linspace(0, 1, 64))[:, :3] * 255).round()


VIRIDIS = _viridis()


def classify(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Masks of the machine (orange: hue 15-45 deg, saturated, not dark) and the soil (within 25 of a colour of the
    height map) in the 3-D canvas, leaving out the side panel, viser's software-WebGL notice and the playback bar."""
    from matplotlib.colors import rgb_to_hsv

    h, w, _ = img.shape
    region = np.ones((h, w), bool)
    region[:, w - 420:] = False
    region[:170, :330] = False
    region[h - 50:, :] = False
    rgb = img.astype(float)
    hsv = rgb_to_hsv(rgb / 255.0)
    hue = hsv[..., 0] * 360
    machine = (hue >= 15) & (hue <= 45) & (hsv[..., 1] > 0.4) & (hsv[..., 2] > 0.3) & region
    px = rgb.reshape(-1, 3)
    d = np.full(len(px), np.inf)
    for c in VIRIDIS:
        d = np.minimum(d, np.abs(px - c).sum(axis=1))
    soil = (d.reshape(h, w) < 25) & region & ~machine
    return machine, soil


@pytest.fixture(scope="module")
def shots(tmp_path_factory):
    folder = tmp_path_factory.mktemp("viewer_shots")
    print(f"\nviewer screenshots: {folder}")
    yield folder
    copy = os.environ.get("OPERA_TAICHI_SHOTS")
    if copy:
        Path(copy).mkdir(parents=True, exist_ok=True)
        for png in folder.glob("*.png"):
            shutil.copy(png, Path(copy) / png.name)


@pytest.fixture(scope="module")
def browser():
    chromium_or_skip()
    with Browser(WIDTH, HEIGHT) as b:
        yield b


def wait_for_scene(browser, path: Path, deadline_s: float = 150.0):
    """Screenshots until the machine and the soil both show; returns the machine mask of the last one."""
    deadline = time.monotonic() + deadline_s
    counts = (0, 0)
    while time.monotonic() < deadline:
        machine, soil = classify(browser.screenshot(path))
        counts = (int(machine.sum()), int(soil.sum()))
        if counts[0] >= MIN_MACHINE and counts[1] >= MIN_SOIL:
            return machine
        time.sleep(1.0)
    pytest.fail(f"the view did not show the machine and the soil in {deadline_s:.0f} s (machine {counts[0]} px, "
                f"soil {counts[1]} px; see {path})")


def wait_for_motion(browser, first: np.ndarray, path: Path, deadline_s: float = 60.0) -> int:
    """Screenshots until the machine's pixels differ from `first` in MIN_MOVED pixels; returns that count."""
    deadline = time.monotonic() + deadline_s
    moved = 0
    while time.monotonic() < deadline:
        machine, soil = classify(browser.screenshot(path))
        moved = int(np.count_nonzero(machine != first))
        if moved >= MIN_MOVED and machine.sum() >= MIN_MACHINE and soil.sum() >= MIN_SOIL:
            return moved
        time.sleep(1.0)
    pytest.fail(f"the machine did not move in {deadline_s:.0f} s ({moved} px changed; see {path})")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_http(url: str, proc, log: Path, deadline_s: float = 150.0) -> None:
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"the server exited ({proc.returncode}): {log.read_text()[-2000:]}")
        try:
            with urllib.request.urlopen(url, timeout=2):
                return
        except OSError:
            time.sleep(0.3)
    pytest.fail(f"nothing served at {url} in {deadline_s:.0f} s")


def stop(proc) -> int | None:
    """SIGTERM, as a job manager stops a run; SIGKILL if it is still there a minute later (a signal that lands in
    Taichi's kernel compilation can be swallowed there). Returns the exit code, None when it had to be killed."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        return None


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A finished coarse excavation (4 s simulated, the arm reaching out and down) recorded with --replay."""
    out = tmp_path_factory.mktemp("viewer_browser") / "run"
    assert cli.main(["run", str(SCENE), "--out", str(out), "--quiet", "--replay", *COARSE,
                     "--set", "sim.duration=4"]) == 0
    return out


# ---------------------------------------------------------------------------------------------- tests
def test_live_view_shows_the_machine_digging(browser, shots, tmp_path):
    port = free_port()
    out, log = tmp_path / "live", tmp_path / "live.log"
    with open(log, "wb") as fh:   # a file, not a pipe: nobody has to drain it
        # paced to the wall clock: the arm moves for the motion's first 25 s whatever the host's speed, and the run
        # outlasts every wait below (it is stopped once the shots are taken), so a run that ended cannot fail it;
        # a browser that takes longer than 25 s to show the scene still fails, on the motion
        proc = subprocess.Popen([sys.executable, str(ROOT / "cli.py"), "run", str(SCENE), "--view", "--view-port",
                                 str(port), "--out", str(out), "--quiet", "--pace", "realtime", *COARSE,
                                 "--set", "sim.duration=600"],
                                stdout=subprocess.DEVNULL, stderr=fh)
    try:
        wait_for_http(f"http://127.0.0.1:{port}", proc, log)
        browser.navigate(f"http://127.0.0.1:{port}")
        first = wait_for_scene(browser, shots / "live_1.png")
        moved = wait_for_motion(browser, first, shots / "live_2.png")
        print(f"live: machine pixels moved {moved}")
        assert proc.poll() is None               # still running: the shots were taken while the arm moved
    finally:
        rc = stop(proc)
    assert rc == 143, log.read_text()[-2000:]                             # SIGTERM: the run folder is closed as interrupted
    assert json.loads((out / "manifest.json").read_text())["status"] == "interrupted"


def test_replay_page_of_a_finished_run(browser, shots, recorded, tmp_path):
    port = free_port()
    log = tmp_path / "view.log"
    with open(log, "wb") as fh:
        proc = subprocess.Popen([sys.executable, str(ROOT / "cli.py"), "view", str(recorded), "--port", str(port)],
                                stdout=subprocess.DEVNULL, stderr=fh)
    try:
        wait_for_http(f"http://127.0.0.1:{port}", proc, log)
        browser.navigate(f"http://127.0.0.1:{port}")
        first = wait_for_scene(browser, shots / "replay_1.png")
        wait_for_motion(browser, first, shots / "replay_2.png")   # it plays on opening, in a loop
    finally:
        rc = stop(proc)
    assert rc == 0, log.read_text()[-2000:]                               # stopping a replay server is not an error


def test_self_contained_html_opens_from_a_file(browser, shots, recorded, tmp_path):
    html = tmp_path / "run.html"
    assert cli.main(["view", str(recorded), "--html", str(html), "--quiet"]) == 0
    text = html.read_text()
    assert "__VISER_EMBED_DATA__" in text and "<script src=" not in text   # nothing to fetch: one file
    browser.navigate(html.as_uri())
    first = wait_for_scene(browser, shots / "html_1.png")
    wait_for_motion(browser, first, shots / "html_2.png")
