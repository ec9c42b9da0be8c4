"""A rotatable 3-D view of the flux map for the HTML report (plotly Mesh3d, WebGL).

The page must open offline from disk, so plotly.js is embedded inline once (about 5 MB)
and the figure's element id is fixed (the same artefacts give the same bytes). Axes are
world millimetres at true scale; the camera (lens disk, optical axis to the focal plane,
the field of view on the focal plane) and the mirrors are drawn where they are.

Faces: coloured by the chosen quantity on observed elements; mid grey where no view
observes the element (unknown, not zero); light grey where the face belongs to no element
(e.g. cylinder caps). A menu switches between the quantities given.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

UNOBSERVED_GREY = "rgb(140,140,140)"
NO_ELEMENT_GREY = "rgb(220,220,220)"


@dataclass
class Rig:
    """What the 3-D view draws besides the subject (world frame, mm)."""

    lens_center_mm: np.ndarray  # (3,)
    look: np.ndarray  # (3,) unit, optical axis into the scene
    up: np.ndarray  # (3,) unit, image up
    lens_radius_mm: float
    focus_distance_mm: float
    field_size_mm: tuple[float, float]  # (width, height) of the field of view on the focal plane
    mirrors: list[tuple[str, np.ndarray]] = field(default_factory=list)  # (name, (4, 3) corners)


def _circle(c, a, b, r, n=48):
    t = np.linspace(0, 2 * np.pi, n + 1)
    return c + r * (np.outer(np.cos(t), a) + np.outer(np.sin(t), b))


def _line(go, pts, name, colour, dash=None, width=4, legend=True):
    pts = np.asarray(pts, float)
    return go.Scatter3d(x=pts[:, 0], y=pts[:, 1], z=pts[:, 2], mode="lines", name=name, showlegend=legend,
                        line=dict(color=colour, width=width, dash=dash), hoverinfo="name")


def _mesh(go, vertices, faces, **kw):
    v, f = np.asarray(vertices, float), np.asarray(faces, int)
    return go.Mesh3d(x=v[:, 0], y=v[:, 1], z=v[:, 2], i=f[:, 0], j=f[:, 1], k=f[:, 2], **kw)


def flux_figure(vertices_mm, faces, element_of_face, observed, layers: dict, *, rig: Rig | None = None,
                title: str = "", outlines: dict | None = None):
    """A plotly Figure of the surface coloured per face, with the rig.

    Parameters
    ----------
    vertices_mm : (V, 3) float
    faces : (F, 3) int
    element_of_face : (F,) int, element or -1.
    observed : (n_elements,) bool
    layers : dict label -> (n_elements,) float
        The quantities the menu offers, first shown first; labels carry their units.
    rig : Rig, optional
    outlines : dict name -> (n_elements,) bool, optional
        Regions of interest, drawn as their boundary lines on the surface.
    """
    import plotly.graph_objects as go

    eof = np.asarray(element_of_face, int)
    obs = np.asarray(observed, bool)
    is_el = eof >= 0
    seen = is_el & obs[np.where(is_el, eof, 0)]
    traces = []
    labels = list(layers)
    if seen.any():
        vals = {k: np.asarray(v, float)[eof[seen]] for k, v in layers.items()}
        first = vals[labels[0]]
        hover = [f"element {e}<br>" + "<br>".join(f"{k}: {vals[k][n]:.4g}" for k in labels)
                 for n, e in enumerate(eof[seen])]
        traces.append(_mesh(go, vertices_mm, np.asarray(faces)[seen], intensity=first, intensitymode="cell",
                            colorscale="Viridis", name="flux", showscale=True, flatshading=True,
                            colorbar=dict(title=dict(text=labels[0], side="right"), len=0.8),
                            cmin=float(np.nanmin(first)), cmax=float(np.nanmax(first)),
                            hovertext=hover, hoverinfo="text",
                            lighting=dict(ambient=0.75, diffuse=0.35, specular=0.05)))
    unseen = is_el & ~seen
    if unseen.any():
        traces.append(_mesh(go, vertices_mm, np.asarray(faces)[unseen], color=UNOBSERVED_GREY, name="unobserved elements",
                            showlegend=True, flatshading=True, hoverinfo="name"))
    if (~is_el).any():
        traces.append(_mesh(go, vertices_mm, np.asarray(faces)[~is_el], color=NO_ELEMENT_GREY,
                            name="faces that are no element", showlegend=True, flatshading=True, hoverinfo="name"))
    if rig is not None:
        traces += _rig_traces(go, rig)
    for k, (name, member) in enumerate((outlines or {}).items()):
        pts = region_outline_mm(vertices_mm, faces, eof, member)
        if len(pts):
            traces.append(_line(go, pts, f"ROI {name}", ROI_COLOURS[k % len(ROI_COLOURS)], width=6))
    fig = go.Figure(traces)
    buttons = []
    if seen.any() and len(labels) > 1:
        for k in labels:
            v = np.asarray(layers[k], float)[eof[seen]]
            ok = np.isfinite(v)
            lo, hi = (float(v[ok].min()), float(v[ok].max())) if ok.any() else (0.0, 1.0)
            buttons.append(dict(label=k, method="restyle",
                                args=[{"intensity": [v.tolist()], "cmin": [lo], "cmax": [hi],
                                       "colorbar.title.text": [k]}, [0]]))
    fig.update_layout(
        title=dict(text=title), height=640, margin=dict(l=0, r=0, t=40, b=0),
        legend=dict(x=0.0, y=0.0, bgcolor="rgba(255,255,255,0.7)"),
        scene=_scene(np.asarray(vertices_mm, float), rig),
        updatemenus=[dict(buttons=buttons, direction="down", x=0.0, y=1.0, xanchor="left", yanchor="top",
                          showactive=True)] if buttons else [])
    return fig


ROI_COLOURS = ("#e6194b", "#f58231", "#ffe119", "#3cb44b", "#4363d8", "#911eb4", "#f032e6", "#000000")


def region_outline_mm(vertices_mm, faces, element_of_face, member) -> np.ndarray:
    """The boundary of a region as line segments (each two points then a NaN row, as plotly
    draws gaps): the edges with a face of the region on one side only."""
    f = np.asarray(faces)
    eof = np.asarray(element_of_face, int)
    inside = (eof >= 0) & np.asarray(member, bool)[np.maximum(eof, 0)]
    if not inside.any():
        return np.zeros((0, 3))
    e = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    flag = np.repeat(inside, 3)
    uniq, inv = np.unique(e, axis=0, return_inverse=True)
    n_in = np.bincount(inv.ravel(), weights=flag, minlength=len(uniq))
    n_all = np.bincount(inv.ravel(), minlength=len(uniq))
    edge = uniq[(n_in > 0) & (n_in < n_all) | ((n_in == 1) & (n_all == 1))]
    v = np.asarray(vertices_mm, float)
    # lifted a little along the vertex normals, so the surface does not hide the line
    t = v[f]
    fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)
    v = v + 0.01 * float(np.linalg.norm(np.ptp(v, axis=0))) * vn
    out = np.full((len(edge), 3, 3), np.nan)
    out[:, 0], out[:, 1] = v[edge[:, 0]], v[edge[:, 1]]
    return out.reshape(-1, 3)


def _scene(vertices_mm: np.ndarray, rig: Rig | None) -> dict:
    """True-scale axes in mm holding the subject and the rig, the view centred on the subject.

    Plotly puts the scene in a box whose sides are ``aspectratio`` (largest 1 here), each axis
    range mapped onto [-a/2, a/2] ... [a/2]; ``camera.center`` and ``eye`` are in those units."""
    pts = [vertices_mm]
    if rig is not None:
        pts.append(np.asarray(rig.lens_center_mm, float)[None])
        pts += [np.asarray(q, float) for _, q in rig.mirrors]
    pts = np.vstack(pts)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    span = np.maximum(hi - lo, 1e-6) * 1.04
    mid = (lo + hi) / 2
    lo, hi = mid - span / 2, mid + span / 2
    aspect = span / span.max()
    c = (vertices_mm.min(axis=0) + vertices_mm.max(axis=0)) / 2
    centre = (c - mid) / span * aspect
    size = float(np.max((vertices_mm.max(axis=0) - vertices_mm.min(axis=0)) / span.max()))
    eye = centre + np.array([1.0, -1.3, 0.9]) * max(size, 0.05) * 1.6
    axis = lambda t, a, b: dict(title=dict(text=t), range=[float(a), float(b)])
    return dict(aspectmode="manual", aspectratio=dict(zip("xyz", map(float, aspect))),
                xaxis=axis("x (mm)", lo[0], hi[0]), yaxis=axis("y (mm)", lo[1], hi[1]),
                zaxis=axis("z (mm)", lo[2], hi[2]),
                camera=dict(center=dict(zip("xyz", map(float, centre))), eye=dict(zip("xyz", map(float, eye)))))


def _rig_traces(go, rig: Rig) -> list:
    look = np.asarray(rig.look, float) / np.linalg.norm(rig.look)
    up = np.asarray(rig.up, float)
    up = up - (up @ look) * look
    up /= np.linalg.norm(up)
    right = np.cross(look, up)
    c = np.asarray(rig.lens_center_mm, float)
    focal = c + rig.focus_distance_mm * look
    w, h = rig.field_size_mm
    corners = np.array([focal + sx * w / 2 * right + sy * h / 2 * up for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1), (-1, -1))])
    out = [_line(go, _circle(c, right, up, rig.lens_radius_mm), "camera lens", "black", width=6),
           _line(go, [c, focal], "optical axis to the focal plane", "black", dash="dash", width=2),
           _line(go, corners, "camera's field on the focal plane", "rgb(80,80,80)", dash="dot", width=3)]
    for name, q in rig.mirrors:
        q = np.asarray(q, float)
        out.append(_mesh(go, q, [[0, 1, 2], [0, 2, 3]], color="rgb(150,190,230)", opacity=0.35,
                         name=f"mirror {name}", showlegend=True, hoverinfo="name"))
        out.append(_line(go, np.vstack([q, q[:1]]), f"mirror {name}", "rgb(60,110,170)", width=3, legend=False))
    return out


def to_html(fig, div_id: str = "flux3d") -> str:
    """The figure as an HTML fragment with plotly.js inline (works offline, fixed ids)."""
    return fig.to_html(full_html=False, include_plotlyjs=True, div_id=div_id,
                       config={"displaylogo": False, "responsive": True})
