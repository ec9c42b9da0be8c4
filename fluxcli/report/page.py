"""The report page: one self-contained HTML file (PNGs embedded as data URIs, inline CSS,
plotly.js inline for the 3-D view, no external links), built from the numbers in summary.json."""

from __future__ import annotations

import base64
import html
from pathlib import Path

CSS = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; max-width: 1180px; margin: 1.5em auto;
       padding: 0 1em; color: #222; line-height: 1.45; }
h1 { margin-bottom: 0.2em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: 0.2em; margin-top: 1.8em; }
figure { margin: 1em 0 1.6em 0; } figure img { max-width: 100%; height: auto; border: 1px solid #eee; }
figcaption { font-size: 0.9em; color: #555; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th { background: #f3f3f3; } td.l, th.l { text-align: left; }
.meta { color: #555; font-size: 0.9em; } .note { background: #fff8e1; padding: 0.5em 0.8em; border-left: 3px solid #f0b400; }
nav a { margin-right: 1em; }
.warnings { background: #fdecea; border-left: 4px solid #d93025; padding: 0.2em 1em; margin: 1em 0; }
.warnings h2 { border: none; margin-top: 0.4em; } .warn { margin: 0.4em 0; } .ok { color: #1e7e34; }
.plot3d { border: 1px solid #ddd; margin: 0.5em 0 1.5em 0; }
"""


def fmt(x, kind: str = "g") -> str:
    """Numbers as the page shows them (the full values are in summary.json)."""
    if x is None:
        return "–"
    if isinstance(x, str):
        return x
    if kind == "%":
        return f"{100 * x:.2f} %"
    if kind == "int":
        return f"{int(x)}"
    return f"{x:.4g}"


def _method(name, settings: dict) -> str:
    """'weighted_lsq: lambda auto (discrepancy)' from the stored settings."""
    if name in ("paper", "tikhonov", "nnls", "weighted_lsq"):
        lam = settings.get("lambda", settings.get("lam"))
        rule = f" ({settings.get('lambda_rule')} rule)" if lam == "auto" else ""
        extra = f", at most {settings.get('max_iter')} iterations" if name == "paper" else ""
        return f"{name}: lambda {lam}{rule}{extra}"
    if name == "mlem":
        return f"mlem: {settings.get('n_iter')} iterations"
    if name == "smooth":
        lam = settings.get("lambda", settings.get("lam"))
        return f"smooth: lambda {'auto (UPRE: GCV with the known noise)' if lam == 'auto' else lam}, {settings.get('max_iter')} iterations"
    return str(name)


def _sigma_text(s: dict) -> str:
    """' ± σ (1 sd: ...)' of the joint (or first pose's) total from the error budget, or ''."""
    b = s.get("budget")
    if not b or not b.get("sigma") or s.get("flux_headline_reason"):  # σ is of the total over observed elements
        return ""
    i = len(b["sigma"]) - 1 if s.get("joint_over_poses") else 0
    parts = [f"photon noise {fmt(b['sigma_noise'][i])}"]
    for key, name in (("sigma_regularisation", "regularisation"), ("sigma_calibration", "calibration")):
        parts.append(f"{name} {fmt(b[key][i])}" if b[key][i] is not None else f"{name} not computed")
    return f" ± {fmt(b['sigma'][i])} (1 sd: " + ", ".join(parts) + ")"


class Page:
    def __init__(self, title: str):
        self.title = title
        self.parts: list = []  # HTML strings, and ("figure", png, caption) embedded at the end
        self.toc: list[tuple[str, str]] = []

    # ------------------------------------------------------------------ blocks
    def header(self, s: dict) -> None:
        self.parts.append(
            "<p>The flux leaving the subject's surface, reconstructed from the images of every pose: how well the "
            "model fits the images, the flux on the surface and around a slice, how steady the total is from pose to "
            "pose" + (", and how the error depends on the signal." if "sweep" in s else ".")
            + " Every number shown here is in summary.json beside this page.</p>")
        rows = [("reconstruction", s.get("reconstruction")), ("images", s.get("images")),
                ("method", _method(s.get("method"), s.get("settings") or {})), ("λ used (joint or first pose)", fmt(s.get("lambda_used"))),
                ("elements", fmt(s.get("n_elements"), "int")), ("pixels (nx × ny)", " × ".join(str(p) for p in s.get("pixels", []))),
                ("views", ", ".join(s.get("views", []))),
                ("total flux, " + ("joint over poses" if s.get("joint_over_poses") else "first pose") + " (photons"
                 + (", over well-observed elements" if s.get("flux_headline_reason") else "") + ")",
                 fmt(s.get("flux_headline_total_photons", s.get("flux_total_photons"))) + _sigma_text(s)
                 + (f" — the total over all observed elements ({fmt(s.get('flux_total_photons'))}) is not pinned down "
                    f"by the data: {s['flux_headline_reason']}" if s.get("flux_headline_reason") else "")),
                ("observed elements", fmt(s.get("flux_observed_fraction"), "%"))]
        if s.get("flux_total_well_observed_photons") is not None:
            rows += [("total over well-observed elements (photons)", fmt(s["flux_total_well_observed_photons"])),
                     ("poorly observed elements (hatched)", fmt(s.get("flux_poorly_observed_fraction"), "%"))]
        if "truth_total_photons" in s:
            rows += [("ground-truth total (photons)", fmt(s["truth_total_photons"])),
                     ("error Σ|b̃ − b| / Σb (all elements; unobserved count as 0)", fmt(s.get("error"), "%")),
                     ("total ratio Σb̃ / Σb (all elements)", fmt(s.get("total_ratio")))]
            if s.get("error_observed") is not None:
                rows += [("error over observed elements", fmt(s["error_observed"], "%")),
                         ("total ratio over observed elements", fmt(s.get("total_ratio_observed")))]
        self.parts.append('<table class="meta">' + "".join(
            f'<tr><th class="l">{html.escape(k)}</th><td class="l">{html.escape(str(v))}</td></tr>' for k, v in rows)
            + "</table>")
        # the warnings are the page's first block (notebook.add_top): listed once, not here again

    def section(self, anchor: str, title: str) -> None:
        self.toc.append((anchor, title))
        self.parts.append(f'<h2 id="{html.escape(anchor)}">{html.escape(title)}</h2>')

    def text(self, text: str) -> None:
        self.parts.append(f"<p>{html.escape(text)}</p>")

    def figure(self, png: Path, caption: str) -> None:
        self.parts.append(("figure", Path(png), caption))  # embedded when the page is written

    def table(self, header: list[str], rows: list[list[str]], *, left_columns: int = 1, caption: str = "") -> None:
        def cell(tag, i, v):
            cls = ' class="l"' if i < left_columns else ""
            return f"<{tag}{cls}>{html.escape(str(v))}</{tag}>"

        out = ["<table>"]
        if caption:
            out.append(f"<caption>{html.escape(caption)}</caption>")
        out.append("<tr>" + "".join(cell("th", i, h) for i, h in enumerate(header)) + "</tr>")
        for r in rows:
            out.append("<tr>" + "".join(cell("td", i, v) for i, v in enumerate(r)) + "</tr>")
        out.append("</table>")
        self.parts.append("".join(out))

    def pose_table(self, s: dict) -> None:
        poses = s["poses"]
        norm = s.get("totals_normalised_by_mean", {})
        cols = [("height (mm)", lambda k, p: fmt(p["height_mm"])), ("rotation (°)", lambda k, p: fmt(p["rotation_deg"]))]
        if "direct_roi_photons" in poses[0]:
            cols.append(("direct ROI (photons)", lambda k, p: fmt(p["direct_roi_photons"])))
        if "backprojection_total" in poses[0]:
            cols.append(("backprojection Σ Tᵀa (a.u., not a flux)", lambda k, p: fmt(p["backprojection_total"])))
        cols.append(("reconstructed total (photons)", lambda k, p: fmt(p["total_photons"])))
        for key, name in (("direct_roi", "ROI / mean"), ("backprojection", "backproj. / mean"),
                          ("reconstruction", "recon. / mean")):
            if norm.get(key) is not None:
                cols.append((name, lambda k, p, key=key: fmt(norm[key][k])))
        cols += [("observed", lambda k, p: fmt(p["observed_fraction"], "%")), ("λ", lambda k, p: fmt(p["lambda"])),
                 ("χ²/pixel", lambda k, p: fmt(p["chi2_per_pixel"]))]
        if "error" in poses[0]:
            cols += [("error", lambda k, p: fmt(p["error"], "%")), ("total ratio", lambda k, p: fmt(p.get("total_ratio")))]
        rows = [[str(k + 1)] + [f(k, p) for _, f in cols] for k, p in enumerate(poses)]
        if s.get("joint_over_poses"):
            row = ["joint", "", ""] + [""] * (len(cols) - 2)
            names = [c for c, _ in cols]
            row[1 + names.index("reconstructed total (photons)")] = fmt(s["flux_total_photons"])
            row[1 + names.index("observed")] = fmt(s["flux_observed_fraction"], "%")
            if "error" in names:
                row[1 + names.index("error")] = fmt(s.get("error"), "%")
                row[1 + names.index("total ratio")] = fmt(s.get("total_ratio"))
            rows.append(row)
        sp = s.get("spreads", {})
        spread_row = ["spread", "", ""] + [""] * (len(cols) - 2)
        names = [c for c, _ in cols]
        for key, col in (("direct_roi", "direct ROI (photons)"), ("backprojection", "backprojection Σ Tᵀa (a.u., not a flux)"),
                         ("reconstruction", "reconstructed total (photons)")):
            if col in names and sp.get(key) is not None:
                spread_row[1 + names.index(col)] = fmt(sp[key], "%")
        rows.append(spread_row)
        self.table(["pose"] + names, rows,
                   caption="Per pose; 'spread' is (max − min) / mean over the poses.")
        eff = [p.get("collection_efficiency") for p in poses]
        if all(e is not None for e in eff) and eff:
            views = list(eff[0])
            self.table(["pose"] + [f"{v}" for v in views],
                       [[str(k + 1)] + [fmt(e[v]) for v in views] for k, e in enumerate(eff)],
                       caption="Collection efficiency per view: area-weighted mean column sum of T (dimensionless).")

    def snr_table(self, t: dict) -> None:
        from .figures import pose_labels

        labels = pose_labels(t["heights_mm"], t["rotations_deg"])
        rows = [[fmt(lv)] + [("–" if v is None else f"{v:.2f} : 1") for v in row]
                for lv, row in zip(t["levels_peak_photons"], t["max_snr"])]
        self.table(["peak flux (photons)"] + labels, rows, caption="Maximum SNR in the simulated images.")

    def sweep_table(self, sw: dict, labels: list[str]) -> None:
        rows = []
        for li, lv in enumerate(sw["levels_peak_photons"]):
            for k, lab in enumerate(labels):
                cells = []
                for i in range(len(sw["methods"])):
                    m, d = sw["mean_error"][i][li][k], sw["sd_error"][i][li][k]
                    cells.append("–" if m is None else f"{100 * m:.2f} ± {100 * (d or 0):.2f} %")
                if all(c == "–" for c in cells):
                    continue
                snr = sw["max_snr"][li][k]
                rows.append([fmt(lv), lab, "–" if snr is None else f"{snr:.2f}"] + cells)
        self.table(["peak flux (photons)", "pose", "max SNR"] + [f"error: {m}" for m in sw["methods"]], rows,
                   left_columns=2, caption=f"Error (mean ± sd over {sw['repeats']} repeats).")

    def notes(self, notes: list[str]) -> None:
        if notes:
            self.section("notes", "Notes")
            self.parts.append("".join(f'<p class="note">{html.escape(n)}</p>' for n in notes))

    # ------------------------------------------------------------------ output
    def html(self, base: Path) -> str:
        body = []
        for p in self.parts:
            if isinstance(p, tuple):
                _, png, caption = p
                data = base64.b64encode((Path(base) / png.name).read_bytes()).decode("ascii")
                body.append(f'<figure><img alt="{html.escape(caption)}" src="data:image/png;base64,{data}">'
                            f"<figcaption>{html.escape(caption)} ({html.escape(png.name)})</figcaption></figure>")
            else:
                body.append(p)
        toc = " ".join(f'<a href="#{html.escape(a)}">{html.escape(t)}</a>' for a, t in self.toc)
        t = html.escape(self.title)
        return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{t}</title>'
                f"<style>{CSS}</style></head><body><h1>{t}</h1><nav>{toc}</nav>\n" + "\n".join(body)
                + "\n</body></html>\n")
