"""Shared helpers of the benchmark scripts: where the data is, tables, output files.

Benchmarks read public meshes from ``../shared/data`` (override with
``BAREESA_SHARED=/path/to/shared``); they are never part of the product.
"""

import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "out"
if str(ROOT) not in sys.path:  # run as `python bench/x.py` from anywhere
    sys.path.insert(0, str(ROOT))


def shared_data(script):
    """The shared data folder, or exit with a clear message naming the script."""
    base = Path(os.environ.get("BAREESA_SHARED", ROOT.parent / "shared"))
    data = base / "data"
    if not data.is_dir():
        sys.exit(f"{script}: benchmark data not found under {data}; "
                 "set BAREESA_SHARED to the folder holding data/")
    return data


def markdown_table(header, rows, floatfmt="{:.4g}"):
    """Rows of values -> a markdown table string."""
    fmt = lambda x: floatfmt.format(x) if isinstance(x, (float, np.floating)) else str(x)  # noqa: E731
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(x) for x in row) + " |" for row in rows]
    return "\n".join(lines)


def report(name, text):
    """Print a benchmark's result and write it to bench/out/<name>.md."""
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"{name}.md").write_text(text + "\n")
    print(text)


def contact_sheet(path, meshes, titles, ncols=None, elev=15, azim=-60):
    """Render meshes [(verts, faces)] side by side with matplotlib into a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(meshes)
    ncols = ncols or n
    nrows = (n + ncols - 1) // ncols
    fig = plt.figure(figsize=(2.6 * ncols, 2.8 * nrows))
    allv = np.concatenate([v for v, _ in meshes])
    lo, hi = allv.min(0), allv.max(0)
    half = (hi - lo).max() / 2
    for i, ((v, f), title) in enumerate(zip(meshes, titles)):
        ax = fig.add_subplot(nrows, ncols, i + 1, projection="3d")
        c = (v.max(0) + v.min(0)) / 2
        ax.plot_trisurf(v[:, 0], v[:, 1], v[:, 2], triangles=f, color="#9fb8d6", edgecolor="none",
                        linewidth=0, shade=True)
        for setter, k in ((ax.set_xlim, 0), (ax.set_ylim, 1), (ax.set_zlim, 2)):
            setter(c[k] - half, c[k] + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elev, azim=azim)
        ax.set_axis_off()
        ax.set_title(title, fontsize=8)
    fig.tight_layout()
    OUT.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
