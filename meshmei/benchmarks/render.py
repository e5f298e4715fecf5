"""Benchmark of the rasterizer: time, peak memory, cost model, and silhouette error against speed.

``python -m meshmei.benchmarks.render`` writes the section "render" of ``docs/benchmarks.md`` and the plots
``docs/render_cost.png`` and ``docs/render_speed_error.png``. Each (mesh, image size) configuration runs in a
fresh subprocess so that its peak resident memory (``ru_maxrss``) belongs to it alone. Nothing is saved for an
interrupted run to resume: its units are timings, and taking some from another run would mix two machine states
in one table.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys

import numpy as np
import torch

from ..render import RenderSettings, camera_from_angles, rasterize, render
from ..render.native import native_status, torch_reference
from ..shapes import initial_mesh, target_mesh
from ._report import benchmark_parser, docs_dir, keep_docs_for_full_runs, machine_line, markdown_table, timeit, timings, write_section

MESHES = {"sphere-1k": ("sphere", 500), "sphere-5k": ("sphere", 2500), "sphere-30k": ("sphere", 13000),
          "bunny": ("bunny", None)}
SIZES = (64, 128, 256)
# quoted from the issue (not measured here): PyTorch3D's CPU rasterizer with soft Phong blending and
# 10 faces per pixel, forward + backward on a 2-core CPU
PAPER = {("sphere-5k", 128): 6.6, ("bunny", 256): 35.0}


def _mesh(key, dtype=torch.float32):
    kind, n = MESHES[key]
    return target_mesh("bunny", dtype=dtype) if kind == "bunny" else initial_mesh(kind, n_vertices=n, dtype=dtype)


def _rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_one(key: str, size: int, repeat: int) -> dict:
    """Time forward and forward+backward of one configuration in this process (call in a fresh one)."""
    V, F = _mesh(key)
    st = RenderSettings(image_size=size)
    W = torch.randn(1, 1, size, size, generator=torch.Generator().manual_seed(0))
    base = _rss_mb()

    def fwd():
        with torch.no_grad():
            render(V, F, settings=st)

    def fwd_bwd():
        X = V.clone().requires_grad_(True)
        (render(X, F, settings=st) * W).sum().backward()

    t_f, best_f = timings(fwd, repeat=repeat)
    t_fb, best_fb = timings(fwd_bwd, repeat=repeat)
    img = render(V, F, settings=st)
    covered = int((img != st.background).sum())
    peak = _rss_mb()  # before the torch code's run, whose pair chunks take memory of their own
    with torch_reference():  # the same render without the compiled kernels, in the same process
        t_fb_torch, _ = timings(fwd_bwd, repeat=repeat)
    return dict(mesh=key, size=size, faces=int(F.shape[0]), fwd=t_f, fwd_bwd=t_fb, best_fwd=best_f,
                best_fwd_bwd=best_fb, peak_mb=peak, base_mb=base, covered=covered, fwd_bwd_torch=t_fb_torch,
                compiled=native_status()["compiled"])


def _subprocess(key, size, repeat, threads):
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    cmd = [sys.executable, "-m", "meshmei.benchmarks.render", "--one", key, str(size), "--repeat", str(repeat),
           "--threads", str(threads)]
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


# ---------------------------------------------------------------------------------------------
def _reference_coverage(V, F, cam, S, sub):
    """Supersampled ray-cast coverage (libigl AABB), ``sub x sub`` rays per pixel."""
    import igl  # deferred, as scipy.ndimage below: the --one processes report peak memory, which it would raise

    eye, R = cam.frame(torch.float64)
    eye, R = eye[0].numpy(), R[0].numpy()
    f = cam.focal_pixels(S)
    g = (np.arange(S)[:, None] + (np.arange(sub) + 0.5)[None, :] / sub).reshape(-1)
    v, u = np.meshgrid(g, g, indexing="ij")
    D = ((u - S / 2) / f)[..., None] * R[0] - ((v - S / 2) / f)[..., None] * R[1] + R[2]
    Vn, Fn = V.double().numpy(), F.numpy()
    tree = igl.AABB()
    tree.init(Vn, Fn)
    I, _, _ = tree.intersect_ray_first(Vn, Fn, np.tile(eye, (S * S * sub * sub, 1)), D.reshape(-1, 3))
    return (I.reshape(S, sub, S, sub) >= 0).mean((1, 3))


def speed_vs_error(size=128, repeat=5):
    """Silhouette coverage error (vs 64-sample ray casting) and forward+backward time per setting."""
    from scipy.ndimage import binary_dilation  # deferred (see _reference_coverage)

    V, F = _mesh("bunny")
    views = [(0.0, 0.0), (60.0, 20.0), (200.0, -30.0)]
    cams = [camera_from_angles(az, el, 2.0) for az, el in views]
    refs = [_reference_coverage(V, F, c, size, 8) for c in cams]
    bands = [binary_dilation((r > 0) & (r < 1), structure=np.ones((3, 3), bool)) for r in refs]
    settings = [("hard (sigma 0.01)", 0.01, 1), ("sigma 0.1", 0.1, 1), ("sigma 0.2 (default)", 0.2, 1),
                ("sigma 0.3", 0.3, 1), ("sigma 0.5", 0.5, 1), ("sigma 1.0", 1.0, 1),
                ("hard, 2x2 supersampled", 0.01, 2), ("hard, 4x4 supersampled", 0.01, 4),
                ("sigma 0.2 (fine px), 2x2 supersampled", 0.2, 2), ("sigma 0.2 (fine px), 4x4 supersampled", 0.2, 4)]
    rows = []
    for label, sigma, k in settings:
        st = RenderSettings(image_size=size * k, sigma=sigma)
        errs = []
        for cam, ref, band in zip(cams, refs, bands):
            cov = rasterize(V, F, camera=cam, settings=st).coverage
            cov = torch.nn.functional.avg_pool2d(cov.unsqueeze(1), k)[0, 0].numpy()
            errs.append(np.abs(cov - ref)[band].mean())
        W = torch.randn(1, 1, size, size)

        def fb():
            X = V.clone().requires_grad_(True)
            img = render(X, F, camera=cams[0], settings=st)
            (torch.nn.functional.avg_pool2d(img, k) * W).sum().backward()

        rows.append(dict(label=label, sigma=sigma, k=k, err=float(np.mean(errs)), time=timeit(fb, repeat=repeat)))
    return rows


# ---------------------------------------------------------------------------------------------
def main(argv=None):
    ap = benchmark_parser(__file__, __doc__)
    ap.add_argument("--one", nargs=2, metavar=("MESH", "SIZE"), help=argparse.SUPPRESS)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    ap.add_argument("--quick", action="store_true", help="fewer repeats (a smoke run)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.one:
        print(json.dumps(run_one(args.one[0], int(args.one[1]), args.repeat)))
        return 0
    keep_docs_for_full_runs(args.quick)  # a smoke run must not overwrite the published numbers and plots
    repeat = 2 if args.quick else args.repeat
    load = os.getloadavg()[0]
    machine = machine_line()
    results = {}
    for threads in (1, args.threads) if args.threads > 1 else (1,):
        for key in MESHES:
            for size in SIZES:
                r = _subprocess(key, size, repeat, threads)
                results[(threads, key, size)] = r
                print(f"threads {threads} {key:11s} {size:4d}px  fwd {1e3 * r['fwd']:8.1f} ms  "
                      f"fwd+bwd {1e3 * r['fwd_bwd']:8.1f} ms  peak {r['peak_mb']:7.0f} MB", flush=True)
    torch.set_num_threads(1)  # the speed/error table is timed single-threaded (see the report)
    se = speed_vs_error(repeat=repeat)
    for r in se:
        print(f"{r['label']:30s} err {r['err']:.4f}  time {1e3 * r['time']:.1f} ms", flush=True)
    body = _report(results, se, machine, load)
    path = write_section("render", body)
    _plots(results, se, args.threads)
    print(f"wrote {path}")
    return 0


def _fit(results, threads):
    """Least-squares ``t = c0 + c1 * faces + c2 * pixels`` for forward+backward time (seconds)."""
    rs = [r for (th, _, _), r in results.items() if th == threads]
    A = np.array([[1.0, r["faces"], r["size"] ** 2] for r in rs])
    y = np.array([r["fwd_bwd"] for r in rs])
    c, *_ = np.linalg.lstsq(A, y, rcond=None)
    pred = A @ c
    r2 = 1 - ((y - pred) ** 2).sum() / ((y - y.mean()) ** 2).sum()
    return c, r2


def _report(results, se, machine, load):
    lines = [f"Written by `python -m meshmei.benchmarks.render`. Machine: {machine}; "
             f"1-minute load average at the start {load:.1f} (other jobs share the cores, so times are noisy).",
             "",
             "Forward (no autograd) and forward+backward (`(render(V, F) * W).sum().backward()`) of the default "
             "scene (overhead camera at distance 2.5, 30 degree field of view, sigma 0.2 px, smooth shading), "
             "CPU float32, median (and best) of repeated runs after a warm-up, with the renderer's compiled "
             "kernels (`meshmei.render.native`; "
             f"{'in use' if all(r.get('compiled') for r in results.values()) else 'NOT in use: no C compiler'}) "
             "and, in the same process, with its torch code (`torch_reference()`). Peak memory is the peak "
             "resident set size of a fresh process that imported torch, built the mesh and ran every "
             "compiled measurement; 'above base' subtracts the resident size before the first render.",
             ""]
    ths = sorted({k[0] for k in results})
    lines += _timing_tables(results, ths) + _cost_and_targets(results, ths) + _speed_error_section(se)
    return "\n".join(lines)


def _threads(th):
    return f"{th} thread{'s' if th > 1 else ''}"


def _timing_tables(results, ths):
    """One table per thread count: times and peak memory of every (mesh, size)."""
    lines = []
    for th in ths:
        rows = []
        for (t, key, size), r in results.items():
            if t != th:
                continue
            paper = PAPER.get((key, size))
            rows.append([key, f"{r['faces']:,}", size, f"{1e3 * r['fwd']:.1f} ({1e3 * r['best_fwd']:.1f})",
                         f"{1e3 * r['fwd_bwd']:.1f} ({1e3 * r['best_fwd_bwd']:.1f})",
                         f"{1e3 * r['fwd_bwd_torch']:.1f} ({r['fwd_bwd_torch'] / r['fwd_bwd']:.1f}x)",
                         f"{r['peak_mb']:.0f}", f"{r['peak_mb'] - r['base_mb']:.0f}",
                         f"{paper:.1f} s (quoted)" if paper else ""])
        lines += [f"**{_threads(th)}**", "",
                  markdown_table(["mesh", "faces", "px", "forward ms median (best)", "fwd+bwd ms median (best)",
                                  "fwd+bwd, torch code (its time over the compiled)", "peak MB", "above base MB",
                                  "paper's renderer, fwd+bwd"], rows), ""]
    return lines


def _cost_and_targets(results, ths):
    """The fitted cost model per thread count, and the issue's targets."""
    lines = []
    for th in ths:
        c, r2 = _fit(results, th)
        lines.append(f"Cost model ({_threads(th)}), least squares over the table: fwd+bwd "
                     f"= {1e3 * c[0]:.1f} ms + {1e6 * c[1]:.2f} us/face x faces + {1e6 * c[2]:.3f} us/pixel x "
                     f"pixels (R^2 = {r2:.3f}).")
    lines.append("")
    for th in ths:
        r5, rb = results.get((th, "sphere-5k", 128)), results.get((th, "bunny", 256))
        if r5 and rb:
            lines.append(f"Targets (issue 3), {_threads(th)}: 5k-face sphere at 128 px fwd+bwd "
                         f"{1e3 * r5['fwd_bwd']:.0f} ms median, {1e3 * r5['best_fwd_bwd']:.0f} ms best (target < "
                         f"100 ms); bunny at 256 px {1e3 * rb['fwd_bwd']:.0f} ms median, "
                         f"{1e3 * rb['best_fwd_bwd']:.0f} ms best (target < 1 s), peak {rb['peak_mb']:.0f} MB (target < 1 GB).")
    lines.append("The paper's renderer numbers (6.6 s and 35 s) are quoted from the issue, not measured here. "
                 "With more threads than free cores, torch's thread pool waits on descheduled threads after "
                 "each of the renderer's many small operations; the single-thread rows are then the relevant ones.")
    return lines


def _speed_error_section(se):
    return ["", "**Speed against silhouette error** (bunny, 128 px, three views): mean |coverage - reference| over "
            "pixels within one pixel of the silhouette, the reference being 8x8 = 64 rays per pixel cast with "
            "libigl's AABB tree; time is fwd+bwd of one view on 1 thread; 'k x k supersampled' renders at k times "
            "the resolution (sigma in fine pixels) and average-pools (the box filter of the pooling is the "
            "area coverage; the hard variants have almost no silhouette gradient).", "",
            markdown_table(["setting", "coverage error", "fwd+bwd ms"],
                           [[r["label"], f"{r['err']:.4f}", f"{1e3 * r['time']:.1f}"] for r in se]),
            "", "![speed vs error](render_speed_error.png) ![cost](render_cost.png)"]


def _plots(results, se, threads):
    out = docs_dir()
    _plot_speed_error(se, out / "render_speed_error.png")
    _plot_cost(results, out / "render_cost.png")


def _plot_speed_error(se, path):
    from matplotlib.figure import Figure  # deferred: matplotlib is heavy, and the --one processes report peak memory

    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    for r in se:
        ax.scatter(1e3 * r["time"], r["err"], color="C1" if r["k"] > 1 else "C0")
        ax.annotate(r["label"], (1e3 * r["time"], r["err"]), fontsize=7, xytext=(4, 2), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("forward + backward time (ms), bunny 128 px")
    ax.set_ylabel("mean |coverage error| on silhouette pixels")
    ax.set_title("meshmei rasterizer: speed vs silhouette error")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def _plot_cost(results, path):
    from matplotlib.figure import Figure  # deferred (see _plot_speed_error)

    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    th = max(k[0] for k in results)
    for key in MESHES:
        rs = [results[(th, key, s)] for s in SIZES if (th, key, s) in results]
        ax.plot([r["size"] ** 2 for r in rs], [1e3 * r["fwd_bwd"] for r in rs], "o-", label=f"{key} ({rs[0]['faces']:,} faces)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("pixels")
    ax.set_ylabel("forward + backward (ms)")
    ax.set_title(f"cost vs image size, CPU float32, {th} thread(s)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    sys.exit(main())
