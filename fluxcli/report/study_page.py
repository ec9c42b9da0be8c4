"""The study page: ROI totals over time per subject, with error bars (plotly, inline and
offline), the set-up flags, and the tidy table — from the rows of ``study.csv`` only."""

from __future__ import annotations

import html

import numpy as np

from .page import Page


def _num(x: str) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return np.nan


def _time_of(r: dict) -> tuple[float | str, str]:
    return (_num(r["day"]), "day") if r["day"] != "" else (r["date"], "date")


def study_page(title: str, header: list[str], rows: list[list], flags: dict[str, str], notes: list[str]) -> str:
    """The HTML page (a string): per subject, a plot of each ROI's joint total (± 1 sd) over
    the days per filter, with the true totals where the images were simulated, and beside it
    the direct-view image sum of each pose (what the image-ROI tools report)."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    recs = [dict(zip(header, r)) for r in rows]
    page = Page(title)
    page.parts.append("<p>Every number on this page is in study.csv beside it (one row per session × region × "
                      "pose, the joint reconstruction as pose <code>joint</code>).</p>")
    if flags or notes:
        page.parts.append('<div class="warnings"><h2>Set-up differences</h2>' + "".join(
            f'<p class="warn">{html.escape(k)}: {html.escape(v)}</p>' for k, v in flags.items())
            + "".join(f'<p class="warn">{html.escape(n)}</p>' for n in notes) + "</div>")
    first = True
    for subject in sorted({r["subject"] for r in recs}):
        page.section(f"subject-{subject}", f"Subject {subject}")
        mine = [r for r in recs if r["subject"] == subject]
        fig = make_subplots(rows=1, cols=2, subplot_titles=(
            "fluxmap: light leaving each region (joint over poses)",
            "image sum over the direct view, per pose (the older number)"))
        for roi in dict.fromkeys(r["roi"] for r in mine):
            for filt in dict.fromkeys(r["filter"] for r in mine):
                j = sorted((r for r in mine if r["roi"] == roi and r["filter"] == filt and r["pose"] == "joint"),
                           key=lambda r: _time_of(r)[0])
                if not j:
                    continue
                x = [_time_of(r)[0] for r in j]
                name = f"{roi}, filter {filt}"
                fig.add_trace(go.Scatter(x=x, y=[_num(r["total_photons_per_s"]) for r in j], mode="lines+markers",
                                         name=name, error_y=dict(type="data", array=[_num(r["sigma_photons_per_s"]) for r in j],
                                                                 visible=True),
                                         hovertext=[r["status"] or "ok" for r in j]), row=1, col=1)
                truth = [_num(r["true_total_photons_per_s"]) for r in j]
                if np.isfinite(truth).any():
                    fig.add_trace(go.Scatter(x=x, y=truth, mode="markers", marker=dict(symbol="x", size=10),
                                             name=f"truth: {name}"), row=1, col=1)
        first_roi = next(iter(dict.fromkeys(r["roi"] for r in mine)))
        for filt in dict.fromkeys(r["filter"] for r in mine):
            per = [r for r in mine if r["roi"] == first_roi and r["filter"] == filt and r["pose"] != "joint"]
            for pose in sorted({r["pose"] for r in per}, key=int):
                pr = sorted((r for r in per if r["pose"] == pose), key=lambda r: _time_of(r)[0])
                fig.add_trace(go.Scatter(x=[_time_of(r)[0] for r in pr],
                                         y=[_num(r["direct_image_photons_per_s"]) for r in pr], mode="lines+markers",
                                         line=dict(dash="dot"),
                                         name=f"image sum, pose {pose} (h {pr[0]['height_mm']} mm, "
                                              f"{pr[0]['rotation_deg']}°), filter {filt}"), row=1, col=2)
        axis = _time_of(mine[0])[1]
        fig.update_xaxes(title_text=axis)
        fig.update_yaxes(title_text="photons/s", row=1, col=1)
        fig.update_yaxes(title_text="photons/s", row=1, col=2)
        fig.update_layout(height=460, margin=dict(l=40, r=10, t=50, b=40), legend=dict(orientation="h", y=-0.25))
        page.parts.append(fig.to_html(full_html=False, include_plotlyjs=first, div_id=f"study-{len(page.toc)}",
                                      config={"displaylogo": False, "responsive": True}))
        first = False
    page.section("table", "Table")
    keep = ["subject", "day", "date", "filter", "roi", "pose", "total_photons_per_s", "sigma_photons_per_s",
            "true_total_photons_per_s", "direct_image_photons_per_s", "observed_share", "status", "setup_flag"]
    page.table(keep, [[r[k] for k in keep] for r in recs], left_columns=6)
    return page.html(base=".")
