"""The figure of a correspondence: landmarks on a few training surfaces, same colour per site.

A check by eye that landmark ``n`` lands on the same anatomical site in every case; each case
is drawn in the reference frame (its similarity to the reference undone) and viewed along the
reference's principal axes, so the panels are comparable. Matplotlib is imported only when a
figure is drawn.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from medseg.correspondence._cohort import CorrespondenceResult


def plot_correspondences(
    result: CorrespondenceResult,
    path: str | os.PathLike,
    *,
    n_cases: int = 4,
    cases: Sequence[int] | None = None,
    dpi: int = 120,
):
    """PNG of the landmarks on a few training surfaces, in the same colour order.

    Each case is drawn in the reference frame (its similarity to the reference undone) so the
    views are comparable; landmark ``n`` has the same colour in every panel.

    Parameters
    ----------
    result : CorrespondenceResult
    path : path-like
        PNG file, written atomically.
    n_cases : int, default 4
        Panels: the reference and the next cases in order (ignored if ``cases`` given).
    cases : sequence of int, optional
        Which cases to draw.

    Returns
    -------
    pathlib.Path
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from medseg.io import atomic_write

    n_total = len(result.surfaces)
    if cases is None:
        others = [i for i in range(n_total) if i != result.reference_index]
        cases = [result.reference_index] + others[: max(0, int(n_cases) - 1)]
    cases = [int(c) for c in cases]
    colours = plt.get_cmap("turbo")(np.linspace(0.05, 0.95, result.n_landmarks))
    # a common view: the reference's principal axes (longest along x, shortest towards the eye)
    ref_v = result.reference_surface[0]
    centre = ref_v.mean(0)
    _, axes = np.linalg.eigh(np.cov((ref_v - centre).T))
    axes = axes[:, ::-1] * np.array([1.0, 1.0, np.linalg.det(axes[:, ::-1])])
    fig = plt.figure(figsize=(3.4 * len(cases), 3.9))
    for panel, c in enumerate(cases):
        mat = result.transforms[c]
        inv = np.linalg.inv(mat[:3, :3])

        def view(p, mat=mat, inv=inv):
            return ((np.asarray(p) - mat[:3, 3]) @ inv.T - centre) @ axes

        verts, faces = result.surfaces[c]
        v = view(verts)
        lm = view(result.landmarks[c])
        ax = fig.add_subplot(1, len(cases), panel + 1, projection="3d", computed_zorder=False)
        ax.plot_trisurf(v[:, 0], v[:, 1], v[:, 2], triangles=faces, color="0.75", alpha=0.35,
                        linewidth=0, shade=True, zorder=1)  # fmt: skip
        ax.scatter(lm[:, 0], lm[:, 1], lm[:, 2], c=colours, s=30, depthshade=False,
                   edgecolors="k", linewidths=0.4, zorder=2, alpha=1.0)  # fmt: skip
        tag = " (reference)" if c == result.reference_index else ""
        ax.set_title(
            f"{result.case_ids[c]}{tag}\nresidual {result.residuals_mm[c]:.2f} mm", fontsize=8
        )
        half = np.abs(v).max() * 0.75
        ax.set_xlim(-half, half)
        ax.set_ylim(-half, half)
        ax.set_zlim(-half, half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=55, azim=-90)
        ax.set_axis_off()
    fig.suptitle(
        f"{result.n_landmarks} landmarks in correspondence: same colour = same landmark "
        "(cases shown in the reference frame)",
        fontsize=9,
        y=0.99,
    )
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.86, wspace=0)
    with atomic_write(Path(path)) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    plt.close(fig)
    return Path(path)
