"""The picture of a calibration, read at a glance: per camera the detected corners (dots, coloured by their
reprojection error) with the reprojected ones (crosses) and the image frame, and the cameras seen from above
with the board positions."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from s3k.rigcal.rig import RigCalibration


def draw_calibration(cal: RigCalibration, path: str | Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    C = len(cal.names)
    fig, axes = plt.subplots(1, C + 1, figsize=(4.2 * (C + 1), 4.2))
    obs, res = cal.observations, cal.adjusted.residuals
    err = np.linalg.norm(res, axis=1)
    vmax = max(2.0, float(np.percentile(err, 99)))
    for c, (ax, name, rep) in enumerate(zip(axes, cal.names, cal.report)):
        W, H = cal.sizes[c]
        sel = obs.cam == c
        uv, proj = obs.uv[sel], obs.uv[sel] + res[sel]
        ax.add_patch(plt.Rectangle((0, 0), W, H, fill=False, color="0.5"))
        ax.scatter(uv[:, 0], uv[:, 1], c=err[sel], s=5, cmap="viridis", vmin=0, vmax=vmax, label="detected")
        ax.scatter(proj[:, 0], proj[:, 1], s=6, marker="x", color="r", linewidths=0.4, label="reprojected")
        # the worst residuals, magnified 20x so they can be seen
        worst = np.argsort(err[sel])[-20:]
        for i in worst:
            ax.plot(
                [uv[i, 0], uv[i, 0] + 20 * res[sel][i, 0]],
                [uv[i, 1], uv[i, 1] + 20 * res[sel][i, 1]],
                color="r",
                lw=0.6,
            )
        ax.set_xlim(-0.02 * W, 1.02 * W)
        ax.set_ylim(1.02 * H, -0.02 * H)
        ax.set_aspect("equal")
        ax.set_title(
            f"{name}: median {rep.median_px:.2f} px, {rep.views} views,\n{rep.corners} corners, "
            f"coverage {rep.coverage:.0%}",
            fontsize=9,
        )
        ax.tick_params(labelsize=7)
        if c == 0:
            ax.legend(loc="lower left", fontsize=7, markerscale=2)
    _from_above(axes[-1], cal)
    fig.suptitle(
        f"s3k calibrate: {cal.board.describe()}; red lines: the 20 worst residuals per camera x20",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _from_above(ax, cal: RigCalibration) -> None:
    """Cameras (centre and viewing direction) and board centres, projected on the plane that the board
    positions span (their two main axes), i.e. seen from above the board."""
    a = cal.adjusted
    centres = np.stack([-R.T @ t for R, t in zip(a.R, a.t)])
    axis = np.stack([R[2] for R in a.R])  # optical axes in the world
    board_mid = cal.board.corners3d().mean(0)
    boards = np.stack([R @ board_mid + t for R, t in a.views])
    normal = np.mean([R[:, 2] for R, _ in a.views], axis=0)
    normal /= np.linalg.norm(normal) + 1e-12
    u = np.cross(normal, [1.0, 0, 0] if abs(normal[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    P = np.stack([u, v], 1)
    cc, bb, dd = centres @ P, boards @ P, axis @ P
    scale = 0.15 * max(np.ptp(np.concatenate([cc, bb]), axis=0).max(), 1e-9)
    ax.scatter(bb[:, 0], bb[:, 1], s=8, color="0.6", label="board positions")
    for name, c, d in zip(cal.names, cc, dd):
        ax.arrow(c[0], c[1], d[0] * scale, d[1] * scale, width=scale * 0.02, color="C0")
        ax.plot(*c, "o", color="C0")
        ax.annotate(name, c, fontsize=9, xytext=(3, 3), textcoords="offset points")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"cameras from above the board (arrows: optical axes), unit {cal.rig().units}", fontsize=9)
    ax.legend(loc="lower left", fontsize=7)
    ax.tick_params(labelsize=7)
