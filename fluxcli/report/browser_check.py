"""Open a report in a real headless browser: screenshot, console messages, a rendered 3-D view.

``python -m fluxcli.report.browser_check REPORT.html SCREENSHOT.png`` (what ``make
check-report`` runs) exits 0 when the page loads with no unexpected console message and
the 3-D view shows the coloured surface; 1 when it does not (the problems are printed);
2 when no Chromium is installed (Debian: ``apt-get install chromium``).

The browser is the distribution's Chromium, headless, software WebGL (SwiftShader), with
no network, sync or component updates and a throw-away profile.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--enable-unsafe-swiftshader",
         "--enable-logging=stderr", "--v=0", "--virtual-time-budget=20000", "--hide-scrollbars"]
# Console lines that are not errors: WebGL performance notes of the software renderer.
BENIGN = ("GPU stall due to ReadPixels", "willReadFrequently")
SCENE_BG = np.array([229, 236, 246])  # plotly's 3-D scene background (#E5ECF6)


def find_chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def screenshot(html: Path, png: Path, *, width: int = 1280, height: int = 2600, chromium: str | None = None,
               timeout_s: float = 180) -> list[str]:
    """Render ``html`` and save the top ``width × height`` pixels to ``png``; returns the console messages."""
    exe = chromium or find_chromium()
    if exe is None:
        raise FileNotFoundError("no chromium on PATH (Debian: apt-get install chromium)")
    png = Path(png).resolve()
    png.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="fluxmap-chromium-") as profile:
        r = subprocess.run([exe, *FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}",
                            f"--screenshot={png}", Path(html).resolve().as_uri()],
                           capture_output=True, text=True, timeout=timeout_s)
    if not png.is_file():
        raise RuntimeError(f"chromium wrote no screenshot (exit {r.returncode}): {r.stderr[-2000:]}")
    return [line for line in r.stderr.splitlines() if ":CONSOLE" in line]


def scene_box(rgb: np.ndarray) -> tuple[int, int, int, int] | None:
    """(top, bottom, left, right) of the plotly 3-D scene's background in a screenshot, or None."""
    bg = np.all(np.abs(rgb[:, :, :3].astype(int) - SCENE_BG) <= 3, axis=2)
    rows, cols = np.flatnonzero(bg.sum(axis=1) > 20), np.flatnonzero(bg.sum(axis=0) > 20)
    if len(rows) == 0 or len(cols) == 0:
        return None
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def coloured_fraction(rgb: np.ndarray) -> float:
    """Fraction of pixels with a clearly saturated colour (the colour-mapped surface)."""
    x = rgb[:, :, :3].astype(int)
    return float(np.mean((x.max(axis=2) - x.min(axis=2)) > 60))


def check(html: Path, png: Path, **kw) -> list[str]:
    """Problems found (empty: the page renders, the 3-D view is not blank, the console is clean)."""
    from matplotlib.image import imread

    console = screenshot(html, png, **kw)
    problems = [f"console: {line}" for line in console if not any(b in line for b in BENIGN)]
    rgb = (imread(png)[:, :, :3] * 255).astype(np.uint8)
    if coloured_fraction(rgb) == 0 or np.all(rgb == rgb[0, 0]):
        problems.append("the screenshot is blank")
    box = scene_box(rgb)
    if box is None:
        problems.append("no 3-D scene was drawn (plotly's scene background is nowhere in the screenshot)")
    else:
        t, b, l, r = box
        frac = coloured_fraction(rgb[t:b, l:r])
        if frac < 0.01:
            problems.append(f"the 3-D view is blank: {frac:.2%} of its pixels are coloured")
    return problems


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print("usage: python -m fluxcli.report.browser_check REPORT.html SCREENSHOT.png", file=sys.stderr)
        return 2
    html, png = Path(args[0]), Path(args[1])
    if not html.is_file():
        print(f"check-report: {html} does not exist (make demo first).", file=sys.stderr)
        return 2
    if find_chromium() is None:
        print("check-report: no Chromium found; on Debian: apt-get update && apt-get install -y chromium", file=sys.stderr)
        return 2
    problems = check(html, png)
    for p in problems:
        print(f"check-report: {p}")
    if not problems:
        rgb = (__import__("matplotlib.image", fromlist=["imread"]).imread(png)[:, :, :3] * 255).astype(np.uint8)
        t, b, l, r = scene_box(rgb)
        print(f"check-report: {html} renders in headless Chromium; no console errors; the 3-D view "
              f"({r - l} x {b - t} px at y = {t}) has {coloured_fraction(rgb[t:b, l:r]):.1%} coloured pixels; "
              f"screenshot {png}")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
