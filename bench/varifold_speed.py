"""Speed, accuracy and memory of the varifold backends at the paper's scale.

    python -m bench.varifold_speed                 # CPU backends (and CUDA ones if a GPU is seen)
    python -m bench.varifold_speed --device cuda   # the GPU backends only
    # both write bench/out/varifold_speed[_cuda].md and bench/results/varifold_speed[--device-cuda].json

Source: the DFAUST body template (13,776 faces) scaled to 1.7 m. Targets of ~55k faces:
(a) face-reference.ply rescaled to the body's size (as in the issue), (b) a "scan" of the body
(template subdivided once = 55,104 faces, 1 mm noise) that overlaps the source as in
registration. sigma = 0.025 (the paper's finest scale), float64, value + gradient w.r.t. the
source vertices. Data: ../shared/data (override with BAREESA_SHARED=/path/to/shared).
"""

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run as `python bench/varifold_speed.py` too (the memory child is)
from bareesa import varifold as V  # noqa: E402
from bench.common import shared_data, table, variant_of, write_results  # noqa: E402

SIGMA = 0.025
DTYPE = torch.float64
DATA = ("varifold_speed", "body/DFAUST_template.ply", "faces/face-reference.ply")  # shared_data's arguments


def load(path):
    m = trimesh.load(path, process=False)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def body(data):
    v, f = load(data / "body" / "DFAUST_template.ply")
    v = v - v.mean(0)
    return v * (1.7 / (v.max(0) - v.min(0)).max()), f


def scan(v, f, times, seed=0):
    for _ in range(times):
        v, f = trimesh.remesh.subdivide(v, f)
    return v + np.random.default_rng(seed).normal(scale=1e-3, size=v.shape), f


def face_target(data, like):
    v, f = load(data / "faces" / "face-reference.ply")
    v = v - v.mean(0)
    diag = lambda a: np.linalg.norm(a.max(0) - a.min(0))  # noqa: E731
    return v * diag(like) / diag(v), f


def tt(a, dev="cpu"):
    return torch.tensor(a, dtype=DTYPE if a.dtype.kind == "f" else torch.long, device=dev)


def sync(dev):
    if torch.device(dev).type == "cuda":
        torch.cuda.synchronize()


def timed(fn, dev, warm=3):
    """(first-call seconds, median of `warm` further calls, median CPU seconds, last result).

    CPU seconds (time.process_time, all threads of this process) are robust to other jobs
    sharing the cores; wall seconds are not."""
    sync(dev)
    t = time.perf_counter()
    out = fn()
    sync(dev)
    first = time.perf_counter() - t
    ts, cs = [], []
    for _ in range(warm):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        sync(dev)
        ts.append(time.perf_counter() - t)
        cs.append(time.process_time() - c)
    return first, statistics.median(ts), statistics.median(cs), out


def value_grad(loss_fn, v):
    v = v.detach().clone().requires_grad_(True)
    d = loss_fn(v)
    (g,) = torch.autograd.grad(d, v)
    return float(d.detach()), g


def dense_torch_estimate(vs, fs, vt, ft, n_sub=3000):
    """Dense torch is minutes at this size: time it against a 3,000-face subsample of the target
    and extrapolate linearly in the number of pairs (loss call: source self + cross terms)."""
    idx = np.random.default_rng(0).choice(ft.shape[0], n_sub, replace=False)
    sub = V.VarifoldLoss(tt(vt), tt(ft[idx]), SIGMA, backend="dense")
    sub(tt(vs), tt(fs))  # warm (target self term)
    v = tt(vs).requires_grad_(True)
    t = time.perf_counter()
    d = sub(v, tt(fs))
    d.backward()
    el = time.perf_counter() - t
    n, m = fs.shape[0], ft.shape[0]
    per_pair = el / (n * n + n * n_sub)
    return per_pair * (n * n + n * m), per_pair * (n * n + n * m + m * m)


def run_case(name, vs, fs, vt, ft, dev, backends, rows):
    ref = None
    S, T = tt(vs, dev), tt(fs, dev)
    for label, backend, use_keops in backends:
        V.kernels._KEOPS = None if use_keops else False
        tv, tf = tt(vt, dev), tt(ft, dev)

        def one_shot():
            return value_grad(lambda v: V.varifold_distance(v, T, tv, tf, SIGMA, backend=backend), S)

        # dense KeOps one-shot is the slowest call by far: one warm call only
        first1, warm1, cpu1, _ = timed(one_shot, dev, warm=1 if backend == "keops" else 3)
        loss = V.VarifoldLoss(tv, tf, SIGMA, backend=backend)
        first2, warm2, cpu2, (val, grad) = timed(lambda: value_grad(lambda v: loss(v, T), S), dev)
        stats = dict(loss.stats)
        if ref is None:
            ref = (val, grad, warm1, warm2, cpu1, cpu2)
        rows.append({
            "case": name, "device": dev, "backend": label, "first_oneshot_s": first1,
            "oneshot_s": warm1, "first_loss_s": first2, "loss_s": warm2,
            "oneshot_cpu_s": cpu1, "loss_cpu_s": cpu2,
            "speedup_oneshot": ref[2] / warm1, "speedup_loss": ref[3] / warm2,
            "cpu_speedup_oneshot": ref[4] / cpu1, "cpu_speedup_loss": ref[5] / cpu2,
            "value": val, "rel_err_value": abs(val - ref[0]) / abs(ref[0]),
            "rel_err_grad": float((grad - ref[1]).norm() / ref[1].norm()),
            "pairs_per_call": stats["pairs"], "all_pairs": stats["all_pairs"]})
        print(json.dumps(rows[-1]), flush=True)
    V.kernels._KEOPS = None


def memory_child(which, data_dir):
    """Run in a subprocess: one truncated VarifoldLoss build + value/grad call on a 220k-face scan."""
    vs, fs = body(Path(data_dir))
    vt, ft = scan(vs, fs, 2, seed=1)
    V.kernels._KEOPS = None if which == "keops" else False
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t = time.perf_counter()
    loss = V.VarifoldLoss(tt(vt), tt(ft), SIGMA, backend="truncated")
    val, _ = value_grad(lambda v: loss(v, tt(fs)), tt(vs))
    el = time.perf_counter() - t
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"faces": int(ft.shape[0]), "peak_mb": peak / 1024, "before_mb": base / 1024,
                      "seconds": el, "value": val}))


def main():
    if len(sys.argv) == 3 and sys.argv[1] == "--memory-child":
        return memory_child(sys.argv[2], shared_data(*DATA))
    parser = argparse.ArgumentParser(description="Speed of the varifold backends at the paper's scale.")
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"),
                        help="cpu: the CPU backends, the CPU memory table, and the CUDA backends when a GPU "
                             "is seen (default); cuda: the CUDA backends alone")
    args = parser.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        sys.exit("varifold_speed: --device cuda, but torch sees no CUDA device")
    data = shared_data(*DATA)
    torch.manual_seed(0)
    vs, fs = body(data)
    targets = {"(a) face-reference rescaled": face_target(data, vs),
               "(b) body scan (subdivided, noise)": scan(vs, fs, 1)}
    print(f"source {fs.shape[0]} faces; targets " +
          ", ".join(f"{k}: {v[1].shape[0]} faces" for k, v in targets.items()) +
          f"; sigma={SIGMA}, cutoff={V.default_cutoff(SIGMA):.4f}, float64, "
          f"torch threads={torch.get_num_threads()}", flush=True)
    rows = []
    cpu_backends = [("keops (dense)", "keops", True), ("truncated (keops ranges)", "truncated", True),
                    ("truncated (torch tiles)", "truncated", False)]
    for name, (vt, ft) in targets.items() if args.device == "cpu" else ():
        run_case(name, vs, fs, vt, ft, "cpu", cpu_backends, rows)
        est_loss, est_one = dense_torch_estimate(vs, fs, vt, ft)
        rows.append({"case": name, "device": "cpu", "backend": "dense torch (estimated)",
                     "oneshot_s": est_one, "loss_s": est_loss,
                     "speedup_oneshot": rows[-3]["oneshot_s"] / est_one,
                     "speedup_loss": rows[-3]["loss_s"] / est_loss})
        print(json.dumps(rows[-1]), flush=True)
    if torch.cuda.is_available():
        for name, (vt, ft) in targets.items():
            # KeOps first (the reference of the speed-ups) when it compiles for CUDA here; dense torch
            # (what "auto" picks on a GPU without pykeops) beside it
            keops = [("keops (dense)", "keops", True), ("truncated (keops ranges)", "truncated", True)]
            run_case(name, vs, fs, vt, ft, "cuda",
                     (keops if V.kernels.keops_available() else []) + [("dense torch", "dense", False)], rows)
    mem = []
    for which in ("keops", "torch") if args.device == "cpu" else ():
        out = subprocess.run([sys.executable, __file__, "--memory-child", which],
                             capture_output=True, text=True)
        line = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
        mem.append((which, json.loads(line[-1]) if line else {"error": out.stderr[-500:]}))
        print(which, mem[-1][1], flush=True)

    md = ["# Varifold backends at the paper's scale", "",
          f"Source: body template, {fs.shape[0]} faces, height 1.7 m. sigma = {SIGMA}, "
          f"cutoff = {V.default_cutoff(SIGMA):.4f} (tol 1e-6), float64, value + gradient w.r.t. "
          f"the source vertices, {torch.get_num_threads()} CPU threads"
          + (f", GPU {torch.cuda.get_device_name()}" if torch.cuda.is_available() else "") + ". Times in seconds: first call "
          "(includes any KeOps compile) / median of 3 warm calls (1 for the dense-KeOps one-shot), wall-clock and CPU seconds (process_time over all threads; robust to other jobs sharing the cores). 'one-shot' = varifold_distance "
          "(recomputes the target self term); 'loss' = VarifoldLoss call (target self term cached). "
          "Speed-up and errors are relative to dense KeOps on the same device.", "",
          "| target | device | backend | one-shot first | one-shot warm (wall / CPU) | loss first "
          "| loss warm (wall / CPU) | speed-up wall (one-shot / loss) | speed-up CPU (one-shot / loss) "
          "| rel. err. d^2 | rel. err. grad | pairs per loss call |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        est = "estimated" in r["backend"]
        f = lambda k, fmt="{:.3g}": fmt.format(r[k]) if k in r else "-"  # noqa: E731
        cpu_sp = (f"{r['cpu_speedup_oneshot']:.1f}x / {r['cpu_speedup_loss']:.1f}x"
                  if "cpu_speedup_loss" in r else "-")
        md.append(f"| {r['case']} | {r['device']} | {r['backend']} | {f('first_oneshot_s')} | "
                  f"{f('oneshot_s')} / {f('oneshot_cpu_s')} | {f('first_loss_s')} | "
                  f"{f('loss_s')} / {f('loss_cpu_s')} | "
                  f"{r['speedup_oneshot']:.1f}x / {r['speedup_loss']:.1f}x | {cpu_sp} | "
                  f"{f('rel_err_value', '{:.1e}')} | "
                  f"{f('rel_err_grad', '{:.1e}')} | "
                  + ("-" if est else f"{r['pairs_per_call'] / 1e6:.1f}M of {r['all_pairs'] / 1e6:.0f}M") + " |")
    md += ["", "dense torch: extrapolated from a 3,000-face subsample of the target "
           "(time per pair x number of pairs)."]
    if mem:
        md += ["", "Peak memory (ru_maxrss of a fresh process: load, build VarifoldLoss, one value+gradient "
               "call) of the truncated backend against a 220k-face scan (body subdivided twice):", "",
               "| truncated via | target faces | peak RSS (MB) | RSS before (MB) | build + call (s) |",
               "|---|---|---|---|---|"]
    for which, m in mem:
        if "error" in m:
            md.append(f"| {which} | error: {m['error'][-200:]!r} | | | |")
        else:
            md.append(f"| {which} | {m['faces']} | {m['peak_mb']:.0f} | {m['before_mb']:.0f} | "
                      f"{m['seconds']:.2f} |")
    text = "\n".join(md) + "\n"
    print(text)
    out = ROOT / "bench" / "out"
    out.mkdir(parents=True, exist_ok=True)
    (out / ("varifold_speed.md" if args.device == "cpu" else "varifold_speed_cuda.md")).write_text(text)
    write_results("varifold_speed", *results_of(rows, mem), variant=variant_of(parser, args))


def slug(text):
    """'truncated (keops ranges)' -> 'truncated_keops_ranges'."""
    return "_".join("".join(c if c.isalnum() else " " for c in text.lower()).split())


def results_of(rows, mem):
    """(figures, tables) of the backend rows and the memory children."""
    figures, table_rows = {}, []
    for r in rows:
        key = f"{'face' if r['case'].startswith('(a)') else 'scan'}_{r['device']}_{slug(r['backend'])}"
        figures |= {f"{key}_oneshot_s": r["oneshot_s"], f"{key}_loss_s": r["loss_s"]}
        if "rel_err_grad" in r and r["rel_err_grad"] > 0:
            figures[f"{key}_rel_err_grad"] = r["rel_err_grad"]
        table_rows.append([r["case"], r["device"], r["backend"], r.get("first_oneshot_s"), r["oneshot_s"],
                           r.get("oneshot_cpu_s"), r.get("first_loss_s"), r["loss_s"], r.get("loss_cpu_s"),
                           r["speedup_loss"], r.get("rel_err_value"), r.get("rel_err_grad"),
                           r.get("pairs_per_call")])
    tables = [table("Varifold value + gradient, speed-up and errors relative to dense KeOps on the same device",
                    ["target", "device", "backend", "one-shot first s", "one-shot warm s", "one-shot CPU s",
                     "loss first s", "loss warm s", "loss CPU s", "speed-up (loss, wall)", "rel. err. d^2",
                     "rel. err. grad", "pairs per loss call"], table_rows)]
    good = [(which, m) for which, m in mem if "error" not in m]
    for which, m in good:
        figures |= {f"memory_truncated_{which}_peak_mb": m["peak_mb"], f"memory_truncated_{which}_s": m["seconds"]}
    if good:
        tables.append(table("Peak memory of the truncated backend against a 220k-face scan (a fresh process)",
                            ["truncated via", "target faces", "peak RSS MB", "RSS before MB", "build + call s"],
                            [[w, m["faces"], m["peak_mb"], m["before_mb"], m["seconds"]] for w, m in good]))
    return figures, tables


if __name__ == "__main__":
    main()
