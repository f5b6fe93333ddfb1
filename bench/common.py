"""Shared helpers of the benchmark scripts: where the data is, tables, output files, results files.

Benchmarks read public meshes from ``../shared/data`` (override with
``BAREESA_SHARED=/path/to/shared``); they are never part of the product. Each writes its markdown
to ``bench/out/`` (``report``) and its numbers to ``bench/results/<bench>[--<variant>].json``
(``write_results``; folder overridable with ``BAREESA_BENCH_RESULTS``), which ``python -m
bench.report`` renders into docs/performance.md and the README.
"""

import hashlib
import json
import math
import os
import platform
import re
import shlex
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "out"
RESULTS = ROOT / "bench" / "results"
if str(ROOT) not in sys.path:  # run as `python bench/x.py` from anywhere
    sys.path.insert(0, str(ROOT))


def shared_data(script, *needs):
    """The shared data folder, or exit with a clear message naming the script (and the files it
    ``needs``, paths relative to the data folder, when one is missing)."""
    base = Path(os.environ.get("BAREESA_SHARED", ROOT.parent / "shared"))
    data = base / "data"
    missing = [n for n in needs if not (data / n).exists()]
    if not data.is_dir() or missing:
        sys.exit(f"{script}: benchmark data not found under {data}"
                 + (f" (expected {', '.join(missing)})" if missing else "")
                 + "; set BAREESA_SHARED to the folder holding data/")
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


# ------------------------------------------------------------------------------ results files


def results_dir():
    """Where results files go: $BAREESA_BENCH_RESULTS, else bench/results."""
    return Path(os.environ.get("BAREESA_BENCH_RESULTS", RESULTS))


def table(title, header, rows):
    """A results table: {"title", "header", "rows"} (rows of plain values)."""
    return {"title": title, "header": [str(h) for h in header], "rows": [list(r) for r in rows]}


def dict_table(title, rows):
    """A results table from a list of dicts: the header is every key in the order first met (a row
    without a key leaves its cell empty)."""
    header = list(dict.fromkeys(k for r in rows for k in r))
    return table(title, header, [[r.get(k) for k in header] for r in rows])


def variant_of(parser, args, ignore=()):
    """'' for a run with the parser's defaults, else the arguments that differ, as a file-name part:
    ``--device cuda --skip matching random`` -> ``device-cuda_skip-matching-random``. Arguments in
    ``ignore`` (those that change where output goes, not what is measured) are left out."""
    parts = []
    for name, value in sorted(vars(args).items()):
        if name in ignore or value == parser.get_default(name):
            continue
        if isinstance(value, (list, tuple, set)):
            value = "-".join(map(str, value)) if value else "none"
        elif isinstance(value, bool):
            value = "on" if value else "off"
        value = value.name if isinstance(value, Path) else value
        parts.append(re.sub(r"[^A-Za-z0-9.+-]+", "-", f"{name}-{value}").strip("-"))
    text = "_".join(parts)
    if len(text) > 80:  # a long argument list: its start and a digest of the whole
        text = f"{text[:71]}_{hashlib.sha1(text.encode()).hexdigest()[:8]}"
    return text


def _plain(x):
    """numpy scalars and arrays -> Python values; NaN and inf -> None; floats to 6 significant digits."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [_plain(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(f"{float(x):.6g}") if math.isfinite(x) else None
    if x is None or isinstance(x, str):
        return x
    return str(x)


def _git(*args):
    out = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=30)
    if out.returncode:
        raise RuntimeError(out.stderr)
    return out.stdout.strip()


def git_commit():
    """(HEAD's short sha, whether tracked files other than the results have uncommitted changes);
    (None, None) without git."""
    try:
        sha = _git("rev-parse", "--short", "HEAD")
        changes = _git("status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)bench/results")
        return sha, bool(changes)
    except (OSError, RuntimeError, subprocess.SubprocessError):
        return None, None


def cpu_name():
    """The CPU's model name (/proc/cpuinfo, else the platform's)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or None


def machine():
    """What a result was measured on: CPU, cores, torch threads, GPU, Python and torch versions."""
    info = {"cpu": cpu_name(), "cores": os.cpu_count(), "threads": None, "gpu": None,
            "python": platform.python_version(), "torch": None}
    try:
        import torch
    except ImportError:
        return info
    info |= {"threads": torch.get_num_threads(), "torch": torch.__version__}
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name()
    return info


def write_results(bench, figures, tables=(), targets=None, *, variant="", labels=None, headline=None,
                  argv=None, folder=None):
    """Write ``<folder>/<bench>.json`` (``<bench>--<variant>.json`` for a run with other arguments).

    figures: flat {name: number}, units in the names (``registration_wall_s``, ``..._mm``,
    ``..._pct_height``); tables: [``table(...)``]; targets: {figure: {"target": value, "better":
    "lower" | "higher"}}; labels: {figure: the words the report shows for it}; headline: the
    figures the README's table shows, in order (default: those with a target). argv: the
    arguments of the run (default sys.argv[1:]); folder: default ``results_dir()``.
    -> the path written."""
    argv = sys.argv[1:] if argv is None else list(argv)
    sha, dirty = git_commit()
    targets = {k: v for k, v in (targets or {}).items() if k in figures}  # a part skipped has no figures
    labels = {k: v for k, v in (labels or {}).items() if k in figures}
    data = {
        "bench": bench,
        "variant": variant,
        "command": " ".join(["python", "-m", f"bench.{bench}", *map(shlex.quote, map(str, argv))]),
        "commit": sha,
        "dirty": dirty,
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": machine(),
        "figures": _plain(dict(figures)),
        "targets": _plain(targets),
        "labels": labels,
        "headline": [k for k in (targets if headline is None else headline) if k in figures],
        "tables": [_plain(t) for t in tables],
    }
    folder = Path(folder) if folder is not None else results_dir()
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / (f"{bench}--{variant}.json" if variant else f"{bench}.json")
    text = json.dumps(data, indent=1, ensure_ascii=False)
    # a list of plain values (a table's header or row) on one line: shorter files, line-by-line diffs
    text = re.sub(r"\[\n\s+([^\[\]{}]*?)\n\s*\]",
                  lambda m: "[" + " ".join(line.strip() for line in m.group(1).splitlines()) + "]", text)
    path.write_text(text + "\n")
    print(f"results written to {path}")
    return path


def contact_sheet(path, meshes, titles, ncols=None, elev=15, azim=-60):
    """Render meshes [(verts, faces) or None: a blank cell] side by side with matplotlib into a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(meshes)
    ncols = ncols or n
    nrows = (n + ncols - 1) // ncols
    fig = plt.figure(figsize=(2.6 * ncols, 2.8 * nrows))
    allv = np.concatenate([m[0] for m in meshes if m is not None])
    lo, hi = allv.min(0), allv.max(0)
    half = (hi - lo).max() / 2
    for i, (mesh, title) in enumerate(zip(meshes, titles)):
        if mesh is None:
            continue
        v, f = mesh
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
