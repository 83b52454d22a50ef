"""PNG plots of one run's metrics, and the fidelity trace of the ablation table (matplotlib, Agg canvas, imported
lazily; no pyplot global state)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

AXES = "xyz"


def _values(curve: list[dict], key: str, scale: float = 1.0) -> np.ndarray:
    return np.array([np.nan if r.get(key) is None else float(r[key]) * scale for r in curve])


def _figure(width: float = 6.4, height: float = 4.0):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=120, layout="constrained")
    return fig, fig.add_subplot()


def _save(fig, path: Path) -> Path:
    from ..io.atomic import atomic_write

    # a bare Figure renders through the Agg canvas for PNG; atomic: a full disk leaves the old plot intact
    return atomic_write(path, lambda f: fig.savefig(f, format="png"))


def _quality_plot(curve: list[dict], x_key: str, x_label: str, path: Path, title: str) -> Path:
    fig, ax = _figure()
    x = _values(curve, x_key)
    ax.plot(x, _values(curve, "psnr"), "o-", ms=3, label="held-out PSNR")
    ax.plot(x, _values(curve, "cvq"), "s-", ms=3, label="CVQ (mean cell PSNR over M(t))")
    ax.set_xlabel(x_label)
    ax.set_ylabel("dB")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best")
    return _save(fig, path)


def _cuc_plot(curve: list[dict], threshold: float, path: Path) -> Path:
    fig, ax = _figure()
    ax.plot(_values(curve, "progress"), _values(curve, "cuc20", 100.0), "o-", ms=3, color="tab:green")
    ax.set_xlabel("source progress p = N_released / N_total")
    ax.set_ylabel(f"CUC@{threshold:g} [% of evaluable cells]")
    ax.set_ylim(-2, 102)
    ax.set_title(f"Causal usable coverage (q_c >= {threshold:g} dB)")
    ax.grid(alpha=0.3)
    return _save(fig, path)


def _cell_map(cells: dict, path: Path) -> Path:
    """Top-down map (paper Fig. 5): each column of cells coloured by the mean final PSNR of its evaluable cells."""
    size, up = float(cells["cell_size"]), int(cells.get("up_axis", 2))
    threshold = float(cells.get("quality_threshold", 20.0))
    a, b = [i for i in range(3) if i != up]
    keys = np.asarray(cells["keys"], dtype=np.int64).reshape(-1, 3)
    q = np.array([np.nan if v is None else v for v in cells["q"]], dtype=np.float64)
    ok = np.asarray(cells["eligible"], bool) & np.asarray(cells["measurable"], bool) & np.isfinite(q)
    fig, ax = _figure(6.4, 5.6)
    if len(keys):
        ka, kb = keys[:, a], keys[:, b]
        a0, b0 = ka.min(), kb.min()
        shape = (kb.max() - b0 + 1, ka.max() - a0 + 1)
        total, count = np.zeros(shape), np.zeros(shape)
        np.add.at(total, (kb[ok] - b0, ka[ok] - a0), q[ok])
        np.add.at(count, (kb[ok] - b0, ka[ok] - a0), 1)
        present = np.zeros(shape, bool)
        present[kb - b0, ka - a0] = True
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
        extent = (a0 * size, (ka.max() + 1) * size, b0 * size, (kb.max() + 1) * size)
        grey = np.where(present & (count == 0), 0.85, np.nan)  # cells with samples that are not evaluable
        ax.imshow(grey, origin="lower", extent=extent, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        im = ax.imshow(mean, origin="lower", extent=extent, cmap="RdYlGn", vmin=threshold - 10, vmax=threshold + 15,
                       interpolation="nearest")
        fig.colorbar(im, ax=ax, label="final cell PSNR q_c [dB] (column mean)", extend="both")
    n_ok = int(ok.sum())
    mean_q = f", mean {np.nanmean(q[ok]):.2f} dB" if n_ok else ""
    ax.set_title(f"Final cell PSNR, top-down ({size:g} m cells)\n{n_ok} evaluable cells{mean_q}; grey: not evaluable",
                 fontsize=10)
    ax.set_xlabel(f"{AXES[a]} [m]")
    ax.set_ylabel(f"{AXES[b]} [m]")
    ax.set_aspect("equal")
    return _save(fig, path)


def write_plots(metrics: dict, out_dir, cells: dict | None = None) -> list[Path]:
    """Write the run's PNG plots into ``out_dir`` and return their paths.

    metrics: a metrics.json dict; uses ``curve`` (list of checkpoint records with t_s, progress, psnr, cvq, cuc20,
    supervised_mpix). cells: the final cell table (a results folder's cells.json; default: ``cells`` in
    ``metrics``, as metrics.json of earlier versions has it). Plots:
    heldout_quality_vs_time.png, heldout_quality_vs_progress.png, heldout_quality_vs_mpix.png,
    cuc20_vs_progress.png, cell_psnr_topdown.png (paper Fig. 5). Plots whose data is absent are skipped.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    curve = metrics.get("curve") or []
    if cells is None:
        cells = metrics.get("cells") or (metrics.get("heldout") or {}).get("cells")
    threshold = float((cells or {}).get("quality_threshold", 20.0))
    paths = []
    if curve:
        paths.append(_quality_plot(curve, "t_s", "mapping time [s] (evaluation excluded)",
                                   out / "heldout_quality_vs_time.png", "Held-out quality over mapping time"))
        paths.append(_quality_plot(curve, "progress", "source progress p = N_released / N_total",
                                   out / "heldout_quality_vs_progress.png", "Held-out quality over source progress"))
        if any(r.get("supervised_mpix") is not None for r in curve):
            paths.append(_quality_plot(curve, "supervised_mpix", "supervised pixels [MPix]",
                                       out / "heldout_quality_vs_mpix.png", "Held-out quality over supervision"))
        paths.append(_cuc_plot(curve, threshold, out / "cuc20_vs_progress.png"))
    if cells:
        paths.append(_cell_map(cells, out / "cell_psnr_topdown.png"))
    return paths


def fidelity_trace_plot(trace: list[dict], path, fixed_curve: list[dict] | None = None) -> Path | None:
    """Backlog, chosen scale and cumulative supervised pixels over updates (the paper's Fig. 6), as a PNG at ``path``.

    trace: a fidelity trace (a results folder's fidelity_trace.csv as
    :func:`~eligsir_o3d.run.results.read_fidelity_trace` reads it: update, backlog, backlog_ema, scale,
    supervised_mpix per row). fixed_curve: the checkpoint curve (metrics.json
    ``curve``: updates, supervised_mpix) of the fixed-resolution ablation, drawn beside it. None without a trace.
    """
    if not trace:
        return None
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 6.5), dpi=120, layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    u = [d["update"] for d in trace]
    axes[0].plot(u, [d["backlog"] for d in trace], lw=0.6, color="0.6", label="backlog")
    axes[0].plot(u, [d["backlog_ema"] for d in trace], lw=1.2, color="tab:red", label="smoothed")
    axes[0].set_ylabel("backlog [frames]")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[1].step(u, [d["scale"] for d in trace], where="post", color="tab:blue")
    axes[1].set_yscale("log", base=2)
    axes[1].set_yticks([0.125, 0.25, 0.5, 1.0], ["1/8", "1/4", "1/2", "1"])
    axes[1].set_ylabel("supervision scale")
    axes[2].plot(u, [d["supervised_mpix"] for d in trace], color="tab:blue", label="EliGSiR")
    pts = [(r["updates"], r["supervised_mpix"]) for r in fixed_curve or [] if r.get("supervised_mpix") is not None]
    if pts:
        axes[2].plot(*zip(*pts), "--", color="tab:orange", label="w/o adaptive fidelity")
    axes[2].set_ylabel("supervised pixels [MPix]")
    axes[2].set_xlabel("optimisation update")
    axes[2].legend(loc="upper left", fontsize=8)
    fig.suptitle("Load-Adaptive Fidelity: backlog, scale and cumulative supervision")
    return _save(fig, Path(path))
