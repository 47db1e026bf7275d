"""Matplotlib figure helpers (BRDF figures for now). Imports matplotlib lazily, Agg-safe."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

__all__ = ["brdf_quantity_figure"]


def brdf_quantity_figure(
    x: np.ndarray,
    panels: Sequence[tuple[str, Mapping[str, np.ndarray]]],
    *,
    xlabel: str,
    title: str,
    columns: Sequence[str],
    log_panels: Sequence[int] = (0,),
):
    """Grid of line plots: one row per quantity, one column per case (e.g. roughness).

    **Arguments:**

    - `x`: abscissa, ``(X,)``.
    - `panels`: ``[(quantity label, {curve label: values (len(columns), X)})]`` per row.
    - `xlabel`, `title`: labels; `columns`: column titles.
    - `log_panels`: rows drawn with a logarithmic y axis.

    **Returns:** the matplotlib ``Figure``.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    nrow, ncol = len(panels), len(columns)
    fig, axes = plt.subplots(
        nrow, ncol, figsize=(4.2 * ncol, 2.8 * nrow), squeeze=False, sharex=True
    )
    for r, (qlabel, curves) in enumerate(panels):
        for c, ctitle in enumerate(columns):
            ax = axes[r, c]
            for lab, vals in curves.items():
                ax.plot(x, np.asarray(vals)[c], label=lab, lw=1.4)
            if r in log_panels:
                ax.set_yscale("log")
            if c == 0:
                ax.set_ylabel(qlabel)
            if r == 0:
                ax.set_title(ctitle, fontsize=10)
            if r == nrow - 1:
                ax.set_xlabel(xlabel)
            ax.grid(alpha=0.3)
    axes[0, -1].legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return fig
