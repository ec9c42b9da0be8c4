"""Make the README's figures (run: make figures).  Builds T through the same code as
``fluxmap build-T`` (the cache under runs/ is reused) and draws:

- docs/img/setup-3d.png: the paper-3d rig seen along the cylinder axis, with the real and
  virtual (mirrored) lenses and focal planes;
- docs/img/image-axes.png: the image of a uniformly glowing cylinder (T times element
  areas), direct and mirror views in one frame, with the world directions of the axes;
- docs/img/sensitivity-2d.png: the paper's Fig. 7, total sensitivity of the line detector
  to each ring element at each stage height.
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from fluxcli import artefacts as A  # noqa: E402
from fluxcli.config import load_config  # noqa: E402
from fluxcli.stages import build_t  # noqa: E402
from fluxcli.stages.context import RunContext  # noqa: E402

OUT = ROOT / "docs" / "img"


def build(config: str, *overrides: str):
    cfg = load_config(ROOT / "configs" / config, list(overrides))
    build_t.run(cfg, RunContext(quiet=True))
    views, placer, todo = build_t.plan(cfg)
    return cfg, views, todo


def setup_3d() -> None:
    cfg, views, todo = build("paper-3d.yaml", "subject.poses.rotations_deg=[0]")
    scene = todo[0][0]
    fig, ax = plt.subplots(figsize=(7.0, 6.0))
    th = np.linspace(0, 2 * np.pi, 200)
    ax.plot(12.5 * np.sin(th), 12.5 + 12.5 * np.cos(th), color="tab:orange", label="cylinder (seen along its axis)")
    st = cfg.model.system.stage
    ax.add_patch(plt.Rectangle((-st.size_mm[1] / 2, -st.thickness_mm), st.size_mm[1], st.thickness_mm, color="0.6", label="stage"))
    colors = {"direct": "k", "left": "tab:blue", "right": "tab:green"}
    for view in views:
        cam = view.camera
        c = cam.center_mm
        half = cam.nx / 2 * cam.focal_pixel_mm
        fp = c + cam.focus_distance_mm * cam.axis
        col = colors.get(view.name, "tab:purple")
        ax.plot(*(np.array([fp - half * cam.down, fp + half * cam.down])[:, 1:].T), color=col, ls="--",
                label=f"{view.name} focal plane")
        ax.plot(c[1], c[2], "o", color=col, ms=6)
        ax.annotate(f"{view.name} lens", (c[1], c[2]), textcoords="offset points", xytext=(6, 6), color=col, fontsize=8)
        if view.mirror is not None:
            m = view.mirror
            ends = np.array([m.center_mm - m.half_size_mm[1] * m.axis_v, m.center_mm + m.half_size_mm[1] * m.axis_v])
            ax.plot(ends[:, 1], ends[:, 2], color=col, lw=4, solid_capstyle="butt")
    ax.set_xlim(-400, 400)
    ax.set_ylim(-200, 360)
    ax.set_aspect("equal")
    ax.set_xlabel("y (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_title("paper-3d: real and virtual lenses, focal planes (dashed)")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(OUT / "setup-3d.png", dpi=110)
    plt.close(fig)


def image_axes() -> None:
    cfg, views, todo = build("paper-3d.yaml", "subject.poses.rotations_deg=[0]")
    scene, pt = todo[0]
    with A.open_artefact(pt.path, "transfer") as f:
        T = A.read_csr(f["T"])
        nx, ny = (int(x) for x in f.attrs["pixels"])
    img = (T @ scene.surface.element_areas_mm2).reshape(ny, nx)  # uniform exitance 1 photon/mm^2
    fig, ax = plt.subplots(figsize=(6.4, 5.6))
    im = ax.imshow(img, cmap="magma", vmin=0, interpolation="nearest")
    cb = fig.colorbar(im, ax=ax, shrink=0.85)
    cb.set_label("photons per pixel for 1 photon mm$^{-2}$ emitted")
    ax.set_xlabel("column (grows along world +x)")
    ax.set_ylabel("row (grows along world -y; row 0 = +y side)")
    for name, y in (("right mirror (+y)", 86), ("direct", 128), ("left mirror (-y)", 170)):
        ax.text(172, y, name, color="w", fontsize=8, va="center")
    ax.set_title("image[row, col] of a uniformly glowing cylinder (paper-3d, rotation 0)")
    fig.tight_layout()
    fig.savefig(OUT / "image-axes.png", dpi=110)
    plt.close(fig)


def sensitivity_2d() -> None:
    cfg, views, todo = build("paper-2d.yaml")
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    for scene, pt in todo:
        with A.open_artefact(pt.path, "transfer") as f:
            col = np.asarray(A.read_csr(f["T"]).sum(axis=0)).ravel()
        angle = (np.arange(len(col)) * 360 / len(col) + 180) % 360 - 180
        order = np.argsort(angle)
        ax.plot(angle[order], col[order], label=f"h = {pt.pose.height_mm:g} mm")
    ax.set_xlabel("element angle from the top of the ring (deg)")
    ax.set_ylabel("sensitivity $\\sum_i T_{ij}$ (dimensionless)")
    ax.set_xlim(-120, 120)
    ax.set_title("line detector's sensitivity to each ring element (paper Fig. 7)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "sensitivity-2d.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    OUT.mkdir(parents=True, exist_ok=True)
    setup_3d()
    image_axes()
    sensitivity_2d()
    print("figures in", OUT)
