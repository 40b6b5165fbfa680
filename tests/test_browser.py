"""The notebook widgets in a real browser: JupyterLab on a loopback port, driven by Debian's chromium.

The test starts a JupyterLab server with a random token on a free 127.0.0.1 port, in a temporary folder with a
small notebook that builds the explorers of the course - the RANSAC explorer of notebook 02 (threshold slider),
the consensus-cube slices of notebook 06 (slice slider) and the noise/cap explorer of notebook 01 - from the same
labkit calls the notebooks make. Playwright (the Python package, no browser download) drives /usr/bin/chromium:
open the notebook, run all cells, wait for the widgets, change each slider as a user would (type a value into
its readout, press Enter), and assert that the widget's report and figure change. A screenshot is written to the
test's temporary folder and, when LABKIT_ARTIFACTS names a folder, there as well.

Skips with the reason where chromium or the playwright package is missing.
"""

from __future__ import annotations

import os
import secrets
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]

WIDGET_CELLS = [
    # notebook 02: the RANSAC explorer on a tripod scene
    """import numpy as np
import labkit
from labkit.synthetic import sphere_on_tripod
from labkit.widgets import consensus_slices_widget, ransac_explorer, sphere_cap_explorer
rng = labkit.setup_notebook()
scene = sphere_on_tripod(n_sphere=400, noise=0.001, rng=1)
explorer = ransac_explorer(scene.points, threshold=0.003, truth=scene.sphere, rng=0, radius_range=(0.05, 0.1))
explorer.add_class("lk-ransac")
explorer""",
    # notebook 06: slices through a consensus cube
    """from labkit.synthetic import als_epochs
pair = als_epochs("xyz", size=(20.0, 20.0), density=4.0, rng=2)
cube = labkit.consensus_cube(pair.source, pair.target, extent=0.3, step=0.03)
slices = consensus_slices_widget(cube, truth=pair.truth[:3, 3])
slices.add_class("lk-slices")
slices""",
    # notebook 01: noise and visible cap
    """cap = sphere_cap_explorer(noise=0.001, cap_deg=60)
cap.add_class("lk-cap")
cap""",
]


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _write_notebook(folder: Path) -> Path:
    nbformat = pytest.importorskip("nbformat")
    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_code_cell(src) for src in WIDGET_CELLS]
    nb.metadata["kernelspec"] = {"display_name": "Python 3", "language": "python", "name": "python3"}
    path = folder / "widgets.ipynb"
    nbformat.write(nb, path)
    return path


@pytest.fixture
def jupyterlab(tmp_path):
    """A JupyterLab server on a free loopback port with a token; yields (base url, token)."""
    pytest.importorskip("jupyterlab")
    _write_notebook(tmp_path)
    port, token = _free_port(), secrets.token_hex(16)
    env = dict(os.environ)
    env.pop("MPLBACKEND", None)  # the kernel gets the inline backend, as for a user
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    env["JUPYTER_RUNTIME_DIR"] = str(tmp_path / ".runtime")
    cmd = [sys.executable, "-m", "jupyterlab", "--no-browser", "--ServerApp.ip=127.0.0.1", f"--ServerApp.port={port}",
           "--ServerApp.port_retries=0", f"--IdentityProvider.token={token}", f"--ServerApp.root_dir={tmp_path}",
           "--LabApp.expose_app_in_browser=True", "--LabApp.news_url=", "--LabApp.extension_manager=readonly",
           "--LabApp.check_for_updates_class=jupyterlab.NeverCheckForUpdate"]
    if hasattr(os, "geteuid") and os.geteuid() == 0:  # CI containers run as root
        cmd.append("--allow-root")
    log = open(tmp_path / "jupyterlab.log", "wb")
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 90
        while True:
            try:
                with urllib.request.urlopen(f"{base}/api/status?token={token}", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                log.flush()
                pytest.fail("JupyterLab did not start:\n" + (tmp_path / "jupyterlab.log").read_text()[-3000:])
            time.sleep(0.5)
        yield base, token, tmp_path
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()


def _state(page, cls):
    """Report text and figure source of the widget box with CSS class ``cls``."""
    return page.evaluate(
        """cls => {
            const box = document.querySelector('.' + cls);
            if (!box) return null;
            const img = box.querySelector('img');
            const html = [...box.querySelectorAll('.widget-html-content')].map(e => e.innerText).join('|');
            return {html: html, img: img ? img.src : '', readouts: [...box.querySelectorAll('.widget-readout')]
                    .map(e => e.innerText)};
        }""",
        cls,
    )


def _wait_changed(page, cls, before, keys=("html", "img"), timeout=120):
    """Poll until every entry in ``keys`` of the widget's state differs from ``before`` (or time runs out)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        now = _state(page, cls)
        if now and now["img"] and all(now[k] != before[k] for k in keys):
            return now
        page.wait_for_timeout(500)
    return _state(page, cls)


def _dismiss_dialogs(page):
    """Close JupyterLab's modal dialogs (e.g. "Build Recommended" for unrelated extensions) with their reject button."""
    for _ in range(5):
        dialog = page.locator(".jp-Dialog")
        if dialog.count() == 0:
            return
        reject = dialog.locator("button.jp-mod-reject")
        if reject.count():
            reject.first.click()
        else:
            page.keyboard.press("Escape")
        page.wait_for_timeout(300)


def _set_readout(page, cls, index, value):
    """Type ``value`` into the readout of the ``index``-th slider of the box, then Enter (as a user does)."""
    _dismiss_dialogs(page)
    readout = page.locator(f".{cls} .widget-readout").nth(index)
    readout.click()
    page.keyboard.press("Control+A")
    page.keyboard.type(str(value))
    page.keyboard.press("Enter")


@pytest.mark.slow
def test_widgets_in_jupyterlab(jupyterlab):
    if CHROMIUM is None:
        pytest.skip("no chromium: install Debian's 'chromium' package (apt-get install chromium)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="the 'playwright' Python package is not installed")
    base, token, folder = jupyterlab
    artifacts = [folder] + ([Path(os.environ["LABKIT_ARTIFACTS"])] if os.environ.get("LABKIT_ARTIFACTS") else [])

    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1800})
            page.goto(f"{base}/lab/tree/widgets.ipynb?token={token}", timeout=120_000)
            page.wait_for_selector(".jp-Notebook .jp-Cell", timeout=120_000)
            page.wait_for_function("window.jupyterapp && window.jupyterapp.commands", timeout=60_000)
            page.wait_for_selector(".jp-Notebook-ExecutionIndicator[data-status='idle'], "
                                   ".jp-Notebook-ExecutionIndicator", timeout=120_000)
            page.wait_for_timeout(2000)  # let the kernel connect
            _dismiss_dialogs(page)
            page.evaluate("window.jupyterapp.commands.execute('notebook:run-all-cells')")

            states = {}
            for cls in ("lk-ransac", "lk-slices", "lk-cap"):
                page.wait_for_selector(f".{cls} img", timeout=300_000)
                page.wait_for_function(f"document.querySelector('.{cls} img').src.length > 0", timeout=120_000)
                states[cls] = _state(page, cls)
            _dismiss_dialogs(page)
            for path in artifacts:
                path.mkdir(parents=True, exist_ok=True)
                page.screenshot(path=str(path / "widgets-before.png"), full_page=True)

            # notebook 02: the RANSAC threshold t (mm), from 3 to 10 mm
            _set_readout(page, "lk-ransac", 0, 10)
            after = _wait_changed(page, "lk-ransac", states["lk-ransac"])
            assert after["html"] != states["lk-ransac"]["html"], "RANSAC report did not change with the threshold"
            assert after["img"] != states["lk-ransac"]["img"], "RANSAC figure did not change with the threshold"
            assert any(r.startswith("10") for r in after["readouts"]), after["readouts"]

            # notebook 06: the slice slider of the consensus cube, to its first cell
            _set_readout(page, "lk-slices", 0, 0)
            after = _wait_changed(page, "lk-slices", states["lk-slices"])
            assert after["img"] != states["lk-slices"]["img"], "cube slice figure did not change with the slider"
            assert after["html"] != states["lk-slices"]["html"], "slice position label did not change"

            # notebook 01: a smaller cap widens the centre's uncertainty
            _set_readout(page, "lk-cap", 1, 20)
            after = _wait_changed(page, "lk-cap", states["lk-cap"])
            assert after["html"] != states["lk-cap"]["html"] and "cap 20 deg" in after["html"], after["html"]

            for path in artifacts:
                page.screenshot(path=str(path / "widgets-after.png"), full_page=True)
            assert (folder / "widgets-after.png").stat().st_size > 10_000
        finally:
            browser.close()
