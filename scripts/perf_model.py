"""A synthetic PFNN-shaped model for the per-layer instruction table
(docs/performance.md): 50 phase tables sampled from a Catmull-Rom spline of
4 random control points (as the PFNN demo's are), small enough that every
gating (constant: all 50 tables; linear: 10; cubic: 4) fits the MODEL
region in int8 and int16. Writes an .npz for `exporter npz`: the 50
tables (for --gating constant or linear), or with --control-points the 4
control points themselves (for --gating cubic).

    python3 scripts/perf_model.py OUT.npz [--control-points] [--input 48 --hidden 128 --output 48]
"""
import argparse

import numpy as np


def catmull_rom(points, t):
    """The PFNN demo's cyclic Catmull-Rom spline of 4 control points at t in [0, 1)."""
    pos = 4 * t
    i = int(pos)
    w = pos - i
    p0, p1, p2, p3 = (points[(i + k - 1) % 4] for k in range(4))
    return (
        p1
        + w * (0.5 * p2 - 0.5 * p0)
        + w * w * (p0 - 2.5 * p1 + 2 * p2 - 0.5 * p3)
        + w * w * w * (1.5 * p1 - 1.5 * p2 + 0.5 * p3 - 0.5 * p0)
    )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--input", type=int, default=48)
    ap.add_argument("--hidden", type=int, default=128)
    ap.add_argument("--output", type=int, default=48)
    ap.add_argument("--seed", type=int, default=12)
    ap.add_argument("--control-points", action="store_true")
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    dims = [a.input, a.hidden, a.hidden, a.output]
    arrays = {
        "Xmean": rng.normal(size=a.input).astype(np.float32),
        "Xstd": rng.uniform(0.2, 3.0, size=a.input).astype(np.float32),
        "Ymean": (3 * rng.normal(size=a.output)).astype(np.float32),
        "Ystd": rng.uniform(0.1, 10.0, size=a.output).astype(np.float32),
    }
    for layer in range(3):
        n_in, n_out = dims[layer], dims[layer + 1]
        sd = 1.5 / np.sqrt(n_in)
        base = rng.normal(size=(n_out, n_in)) * sd
        w_pts = [base + 0.4 * sd * rng.normal(size=base.shape) for _ in range(4)]
        b_pts = [0.1 * rng.normal(size=n_out) for _ in range(4)]
        if a.control_points:
            w_tables, b_tables = w_pts, b_pts
        else:
            ts = np.arange(50) / 50
            w_tables = [catmull_rom(w_pts, t) for t in ts]
            b_tables = [catmull_rom(b_pts, t) for t in ts]
        arrays[f"W{layer}"] = np.stack(w_tables).astype(np.float32)
        arrays[f"b{layer}"] = np.stack(b_tables).astype(np.float32)
    np.savez(a.out, **arrays)


if __name__ == "__main__":
    main()
