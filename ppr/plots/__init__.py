"""Matplotlib figures of the library's results and of the ``ppr`` commands' outputs.
Imports matplotlib lazily (Agg unless a backend is already chosen); the demo figure writers
``brdf_figures``, ``double_figures`` and ``pulse_figures`` (``ppr demo``) load the library on
first use."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

__all__ = [
    "brdf_figures",
    "double_figures",
    "pulse_figures",
    "brdf_quantity_figure",
    "plot_brdf_sweep",
    "plot_classification",
    "plot_fit",
    "plot_profiles",
]

# demo figure writers: (module, name), imported on first use (they import JAX)
_LAZY = {
    "brdf_figures": ("._demo", "brdf_figures"),
    "double_figures": ("._double", "double_figures"),
    "pulse_figures": ("._pulse", "pulse_figures"),
}


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'ppr.plots' has no attribute {name!r}")
    import importlib

    module, attr = _LAZY[name]
    return getattr(importlib.import_module(module, __name__), attr)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


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
    plt = _pyplot()
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


def plot_brdf_sweep(path, inc, bis, mueller, quants, title: str) -> None:
    """``ppr brdf``'s figure: M00 [1/sr] and the polarimetric quantities against the
    bistatic angle, one curve per incidence angle (degrees)."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 5, figsize=(20, 4), constrained_layout=True)
    panels = [("M00 [1/sr]", mueller[..., 0, 0])] + [
        (k.replace("_", " ") + (" [rad]" if k == "retardance" else ""), v)
        for k, v in quants.items()
    ]
    for ax, (label, data) in zip(axes, panels, strict=True):
        for i, a in enumerate(inc):
            ax.plot(bis, data[i], label=f"incidence {a:g} deg")
        ax.set_xlabel("bistatic angle [deg]")
        ax.set_title(label)
        if label.startswith("M00") and np.any(np.nan_to_num(data) > 0):
            ax.set_yscale("log")
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_profiles(path, data, range_m, kind: str, labels, title) -> None:
    """Range-resolved returns: the 16 Mueller elements (``kind="mueller"``, data
    ``(4, 4, bins)``) or one curve per Stokes state / channel, against one-way range [m]."""
    plt = _pyplot()
    r = range_m
    if kind == "mueller":
        fig, axes = plt.subplots(4, 4, figsize=(12, 9), sharex=True)
        fig.subplots_adjust(left=0.07, right=0.98, bottom=0.07, top=0.93, hspace=0.3, wspace=0.3)
        for i in range(4):
            for j in range(4):
                ax = axes[i, j]
                ax.plot(r, data[i, j], lw=1)
                ax.set_title(f"M{i}{j}", fontsize=9)
                ax.tick_params(labelsize=7)
        for ax in axes[-1]:
            ax.set_xlabel("range [m]")
    else:
        rows = data.reshape(-1, data.shape[-1]) if kind == "channels" else data[:, 0]
        fig, ax = plt.subplots(figsize=(8, 4.5))
        for lab, row in zip(labels, rows, strict=False):
            ax.plot(r, row, label=str(lab))
        ax.set_xlabel("range [m]")
        ax.set_ylabel("return per bin [m^2/sr]")
        ax.legend(fontsize=8)
    fig.suptitle(f"{title}: range-resolved return ({kind})")
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_classification(path, data, signatures, index, shift, score) -> None:
    """``ppr classify``'s figure: the histogram of best scores, and observation 0 against
    its best template (``signatures[index[0, 0]]``) moved by its range shift (bins)."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.14, top=0.88, wspace=0.25)
    best = np.asarray(score[:, 0], np.float64)
    best = best[np.isfinite(best)]
    if best.size:
        lo, hi = float(best.min()), float(best.max())
        if hi - lo <= 1e-9 * max(1.0, abs(hi)):  # equal scores: one bar, not 20 empty ones
            lo, hi = lo - 5e-4, hi + 5e-4
        axes[0].hist(best, bins=20, range=(lo, hi), color="0.5")
    axes[0].set_xlabel("best score")
    axes[0].set_ylabel("observations")
    x = data[0] / max(float(data[0].sum()), 1e-300)
    y = signatures[index[0, 0]]
    axes[1].plot(x.sum(0), label="observation 0 (all channels)")
    axes[1].plot(np.roll(y.sum(0), int(round(shift[0, 0]))), "--", label="best template, shifted")
    axes[1].set_xlabel("range bin")
    axes[1].legend(fontsize=8)
    fig.suptitle("ppr classify")
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_fit(path, data, fitted) -> None:
    """Counts per range bin of each channel: the data (dots) and the fitted model (lines)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 4))
    for ch in range(data.shape[0]):
        ax.plot(data[ch], ".", ms=3, label=f"channel {ch} data")
        ax.plot(fitted[ch], "-", lw=1)
    ax.set_xlabel("range bin")
    ax.set_ylabel("counts")
    ax.legend(fontsize=7, ncol=2)
    ax.set_title("ppr invert: data (dots) and best fit (lines)")
    fig.savefig(path, dpi=90)
    plt.close(fig)
