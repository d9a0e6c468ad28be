"""Pictures people would rather look at than read: bird's-eye views and range images (PNG)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .labels import LABEL_COLORS, LABEL_NAMES


def pyplot():
    """matplotlib.pyplot on the Agg backend (no screen), imported on first use."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_png(fig, path: str | Path) -> Path:
    """Write a figure as PNG atomically and close it."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    pyplot().close(fig)
    return path


def bev_png(path: str | Path, xyz: np.ndarray, *, labels: np.ndarray | None = None,
            values: np.ndarray | None = None, value_name: str = "range [m]", extent: float | None = None,
            title: str = "", point_size: float = 0.3, sensor_xy=(0.0, 0.0)) -> Path:
    """Top-down scatter of (N, 3) points (x forward/right on the page, y up), coloured by
    semantic label (with a legend of the classes present) or by a scalar (with a colour bar)."""
    plt = pyplot()
    xyz = np.asarray(xyz, np.float64)
    fig, ax = plt.subplots(figsize=(8, 8), dpi=120)
    order = np.argsort(xyz[:, 2]) if len(xyz) else np.zeros(0, int)  # high points drawn last
    p = xyz[order]
    if labels is not None:
        lab = np.asarray(labels)[order].astype(int)
        ax.scatter(p[:, 0], p[:, 1], s=point_size, c=LABEL_COLORS[lab] / 255.0, linewidths=0)
        present = np.unique(lab)
        handles = [plt.Line2D([], [], marker="o", ls="", color=LABEL_COLORS[i] / 255.0, label=LABEL_NAMES[i])
                   for i in present]
        ax.legend(handles=handles, loc="upper right", fontsize=7, markerscale=1.5, framealpha=0.8)
    else:
        val = np.linalg.norm(p[:, :2], axis=1) if values is None else np.asarray(values)[order]
        sc = ax.scatter(p[:, 0], p[:, 1], s=point_size, c=val, cmap="viridis", linewidths=0)
        fig.colorbar(sc, ax=ax, fraction=0.04, label=value_name)
    ax.plot([sensor_xy[0]], [sensor_xy[1]], "r^", ms=8)
    if extent is not None:
        ax.set_xlim(sensor_xy[0] - extent, sensor_xy[0] + extent)
        ax.set_ylim(sensor_xy[1] - extent, sensor_xy[1] + extent)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return save_png(fig, path)


def bev_compare_png(path: str | Path, panels: dict[str, tuple[np.ndarray, np.ndarray | None]], *,
                    extent: float = 45.0, value_name: str = "", title: str = "", point_size: float = 0.3) -> Path:
    """Top-down views side by side: name -> ((N, 3) points, sensor frame; (N,) values or None).
    Panels without values are coloured by height (z), those with values by them (magma, one shared
    colour bar); same axes everywhere, the sensor at the origin."""
    plt = pyplot()
    n = len(panels)
    fig, axes = plt.subplots(1, n, figsize=(6.2 * n, 6.6), dpi=110, squeeze=False)
    z_all = np.concatenate([np.asarray(p, np.float64)[:, 2] for p, v in panels.values() if v is None and len(p)]
                           or [np.zeros(1)])
    zlo, zhi = np.percentile(z_all, [1, 99])
    for ax, (name, (pts, vals)) in zip(axes[0], panels.items()):
        pts = np.asarray(pts, np.float64)
        order = np.argsort(pts[:, 2]) if len(pts) else np.zeros(0, int)
        p = pts[order]
        if vals is None:
            sc = ax.scatter(p[:, 0], p[:, 1], s=point_size, c=p[:, 2], cmap="viridis", vmin=zlo, vmax=zhi,
                            linewidths=0)
            fig.colorbar(sc, ax=ax, fraction=0.04, label="height z [m]")
        else:
            sc = ax.scatter(p[:, 0], p[:, 1], s=point_size, c=np.asarray(vals)[order], cmap="magma_r", vmin=0,
                            linewidths=0)
            fig.colorbar(sc, ax=ax, fraction=0.04, label=value_name)
        ax.plot([0.0], [0.0], "r^", ms=7)
        ax.set_xlim(-extent, extent)
        ax.set_ylim(-extent, extent)
        ax.set_aspect("equal")
        ax.set_title(f"{name} ({len(pts)} points)", fontsize=9)
        ax.set_xlabel("x [m]")
        ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("y [m]")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_png(fig, path)


def mosaic_png(path: str | Path, images: dict[str, np.ndarray], *, title: str = "", cols: int = 3) -> Path:
    """Camera images (name -> (H, W, 3) uint8) in a grid, titled by name."""
    plt = pyplot()
    n = len(images)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 3.6 * rows), dpi=100, squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (name, img) in zip(axes.ravel(), images.items()):
        ax.imshow(img)
        ax.set_title(name, fontsize=9)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_png(fig, path)


def voxel_bev_png(path: str | Path, ijk: np.ndarray, labels: np.ndarray, voxel_size: float, *,
                  corner=(0.0, 0.0, 0.0), visible: np.ndarray | None = None, title: str = "") -> Path:
    """Top view of a voxel grid: each column shows the class of its highest voxel; with
    `visible`, a second panel shows which voxels the input cameras saw."""
    plt = pyplot()
    ijk = np.asarray(ijk, np.int64)
    n = int(ijk[:, :2].max()) + 1 if len(ijk) else 1
    order = np.lexsort((ijk[:, 2], ijk[:, 1], ijk[:, 0]))
    top = np.r_[ijk[order][1:, 0] != ijk[order][:-1, 0], True] | np.r_[ijk[order][1:, 1] != ijk[order][:-1, 1], True]
    sel = order[top]
    img = np.ones((n, n, 3))
    img[ijk[sel, 0], ijk[sel, 1]] = LABEL_COLORS[labels[sel]] / 255.0
    panels = [("class of the highest voxel", img)]
    if visible is not None:
        vis = np.full((n, n, 3), 1.0)
        vis[ijk[:, 0], ijk[:, 1]] = (0.75, 0.75, 0.75)
        v = ijk[visible]
        vis[v[:, 0], v[:, 1]] = (0.85, 0.2, 0.1)
        panels.append((f"seen by the input cameras ({visible.mean() * 100:.0f} % of voxels)", vis))
    fig, axes = plt.subplots(1, len(panels), figsize=(7.5 * len(panels), 7.5), dpi=100, squeeze=False)
    ext = [corner[1], corner[1] + n * voxel_size, corner[0], corner[0] + n * voxel_size]
    for ax, (name, im) in zip(axes[0], panels):
        # x forward is up on the page, y left is left: show (i, j) with i upwards and j flipped
        ax.imshow(im[::-1, ::-1], extent=[ext[1], ext[0], ext[2], ext[3]], interpolation="nearest")
        ax.set_xlabel("y [m] (left)")
        ax.set_ylabel("x [m] (forward)")
        ax.set_title(name, fontsize=10)
    present = np.unique(labels)
    handles = [plt.Line2D([], [], marker="s", ls="", color=LABEL_COLORS[i] / 255.0, label=LABEL_NAMES[i]) for i in present]
    axes[0, 0].legend(handles=handles, loc="lower left", fontsize=7, framealpha=0.85)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_png(fig, path)


def fidelity_png(path: str | Path, images: dict[str, np.ndarray], *, title: str = "", error_m: float = 0.5,
                 mismatch: np.ndarray | None = None) -> Path:
    """Range images one above the other: the ranges (turbo, shared scale, black = no return) and
    any row named 'error ...' as a signed difference (blue nearer, red farther, clipped at
    +-`error_m`); `mismatch` (rows, cols) bool marks in black the cells where only one of the
    two returns, white where neither does."""
    plt = pyplot()
    n = len(images)
    fig, axes = plt.subplots(n, 1, figsize=(14, 1.9 * n + 0.8), dpi=110, squeeze=False)
    ranges = [v for k, v in images.items() if not k.startswith("error")]
    finite = np.concatenate([r[np.isfinite(r)] for r in ranges]) if ranges else np.zeros(1)
    vmax = float(np.percentile(finite, 99)) if finite.size else 1.0
    for ax, (name, img) in zip(axes[:, 0], images.items()):
        if name.startswith("error"):
            cmap = plt.get_cmap("coolwarm").with_extremes(bad="white")
            im = ax.imshow(np.clip(img, -error_m, error_m), aspect="auto", interpolation="nearest", cmap=cmap,
                           vmin=-error_m, vmax=error_m)
            if mismatch is not None:
                ax.imshow(np.where(mismatch, 0.0, np.nan), aspect="auto", interpolation="nearest", cmap="gray",
                          vmin=0, vmax=1)
            fig.colorbar(im, ax=ax, fraction=0.02, pad=0.01, label="m (black: one returns)")
        else:
            cmap = plt.get_cmap("turbo").with_extremes(bad="black")
            im = ax.imshow(img, aspect="auto", interpolation="nearest", cmap=cmap, vmin=0, vmax=vmax)
            fig.colorbar(im, ax=ax, fraction=0.02, pad=0.01, label="range [m]")
        ax.set_title(name, fontsize=9, loc="left")
        ax.set_yticks([])
    axes[-1, 0].set_xlabel("column (azimuth)")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_png(fig, path)


def intensity_png(path: str | Path, images: dict[str, np.ndarray], *, title: str = "",
                  captions: dict[str, str] | None = None) -> Path:
    """Intensity range images one above the other ('real' first, then each simulation), on one
    shared 0-1 scale (the 99th percentile of the real image tops the colour map; black = no
    return), with an optional caption per image (its metrics)."""
    plt = pyplot()
    n = len(images)
    fig, axes = plt.subplots(n, 1, figsize=(14, 1.9 * n + 0.8), dpi=110, squeeze=False)
    real = images.get("real")
    finite = real[np.isfinite(real)] if real is not None else np.zeros(0)
    vmax = float(np.percentile(finite, 99)) if finite.size else 1.0
    cmap = plt.get_cmap("inferno").with_extremes(bad="black")
    for ax, (name, img) in zip(axes[:, 0], images.items()):
        im = ax.imshow(img, aspect="auto", interpolation="nearest", cmap=cmap, vmin=0, vmax=max(vmax, 1e-6))
        fig.colorbar(im, ax=ax, fraction=0.02, pad=0.01, label="intensity (0-1)")
        label = name if name == "real" else f"simulated: {name}"
        if captions and name in captions:
            label += f"  ({captions[name]})"
        ax.set_title(label, fontsize=9, loc="left")
        ax.set_yticks([])
    axes[-1, 0].set_xlabel("column (azimuth)")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_png(fig, path)


def sweeps_over_image_png(path: str | Path, image: np.ndarray, panels: dict[str, tuple[np.ndarray, np.ndarray]], *,
                          title: str = "", value_name: str = "range [m]", vmax: float | None = None,
                          error_panel: str | None = None, error_m: float = 1.0) -> Path:
    """Points drawn over one camera image, one panel per entry, stacked: panels name -> (uv (N, 2)
    pixel coordinates, value (N,)); values on a shared turbo scale (0 to `vmax`, default their
    99th percentile), except the panel named `error_panel`, whose values are clipped at
    `error_m` (a magnitude: light yellow 0 to dark purple `error_m` or more)."""
    plt = pyplot()
    h, w = image.shape[:2]
    n = len(panels)
    fig, axes = plt.subplots(n, 1, figsize=(12, (12 * h / w) * n + 0.9), dpi=110, squeeze=False)
    values = [v for k, (_, v) in panels.items() if k != error_panel and len(v)]
    finite = np.concatenate(values) if values else np.zeros(1)
    finite = finite[np.isfinite(finite)]
    vmax = float(vmax) if vmax is not None else (float(np.percentile(finite, 99)) if finite.size else 1.0)
    for ax, (name, (uv, v)) in zip(axes[:, 0], panels.items()):
        ax.imshow(image, interpolation="nearest")
        if name == error_panel:
            sc = ax.scatter(uv[:, 0], uv[:, 1], c=np.minimum(v, error_m), s=1.5, cmap="magma_r", vmin=0,
                            vmax=error_m, linewidths=0)
            fig.colorbar(sc, ax=ax, fraction=0.02, pad=0.01, label=f"|error| [m] ({error_m:g} = or more)")
        else:
            sc = ax.scatter(uv[:, 0], uv[:, 1], c=v, s=1.5, cmap="turbo", vmin=0, vmax=vmax, linewidths=0)
            fig.colorbar(sc, ax=ax, fraction=0.02, pad=0.01, label=value_name)
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_title(f"{name} ({len(v)} points)", fontsize=9, loc="left")
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_png(fig, path)
