"""Pieces of the self-contained HTML reports (the demo's, the fit's): figures embedded as base64 PNG,
tables, the page style, and the stiffness-fit figure both reports show."""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure

if TYPE_CHECKING:
    from .fitting import StiffnessFit

__all__ = ["STYLE", "page", "png", "section", "stiffness_figure", "table"]

STYLE = """body{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}
img{max-width:100%;display:block;margin:0.5em 0 1.5em}table{border-collapse:collapse;margin:0.5em 0 1.5em}
td,th{border:1px solid #bbb;padding:0.25em 0.6em;text-align:right}th{background:#eee}
pre{background:#f6f6f6;padding:0.6em;overflow-x:auto}
#summary{font-size:1.05em;background:#f4f8ff;border-left:4px solid #36c;padding:0.8em 1em}"""
"""The reports' CSS."""


def page(title: str, body: str) -> str:
    """A whole HTML document: ``title`` (escaped), the reports' style and ``body`` (HTML)."""
    return (
        f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
        f"<style>{STYLE}</style></head><body>{body}</body></html>\n"
    )


def png(figure: Figure) -> str:
    """The figure as a base64 PNG string."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100, bbox_inches="tight")
    return base64.b64encode(buffer.getvalue()).decode("ascii")


def table(header: tuple[str, ...], rows: Sequence[tuple[str, ...]]) -> str:
    """An HTML table of text cells (escaped)."""
    head = "".join(f"<th>{html.escape(cell)}</th>" for cell in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(cell)}</td>" for cell in row) + "</tr>" for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def section(title: str, text: str, figure: Figure, alt: str) -> str:
    """A heading, a paragraph and the figure embedded as an image."""
    return (
        f"<h2>{html.escape(title)}</h2><p>{html.escape(text)}</p>"
        f'<img src="data:image/png;base64,{png(figure)}" alt="{html.escape(alt)}">'
    )


def stiffness_figure(fits: Sequence[StiffnessFit], titles: Sequence[str]) -> Figure:
    """Force against probe displacement of each palpation with its polynomial fits (paper Fig. 4),
    each order's R^2 in the legend; one panel per fit, titled ``title: k = mean ± sd N/m``."""
    figure = Figure(figsize=(4.2 * len(fits), 3.4))
    axes = np.atleast_1d(figure.subplots(1, len(fits)))
    for axis, title, fit in zip(axes, titles, fits, strict=True):
        lam = np.linspace(fit.probe_displacement_mm.min(), fit.probe_displacement_mm.max(), 200)
        axis.plot(fit.probe_displacement_mm, fit.force_n, ".", color="0.5", label="samples")
        for order, coefficients in fit.polynomials.items():
            axis.plot(lam, np.polyval(coefficients, lam), label=f"order {order} (R² = {fit.r_squared[order]:.4f})")
        mean, sd = fit.stiffness_mean_sd_n_per_m
        axis.set(title=f"{title}: k = {mean:.0f} ± {sd:.0f} N/m", xlabel="λ_z (mm)", ylabel="force (N)")
        axis.legend(fontsize=7)
    figure.tight_layout()
    return figure
