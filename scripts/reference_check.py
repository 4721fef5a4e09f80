#!/usr/bin/env python3
"""Independent NumPy check of phasegate's float PFNN reference.

Written from the published formulas (shared/pfnn/README.md), not from the Rust
code. Loads the .bin weight directory itself, runs the network on X.npy (N x
input, raw units) at P.npy (N phases, radians, wrapped into [0, 2pi)) and
compares with Y.npy (N x output, from the Rust reference). Gating: constant =
table floor(p/2pi * T); linear = every (T/10)-th table as 10 keyframes blended
linearly (all T if T is not a multiple of 10); cubic = exact Catmull-Rom spline
at s = 4p/2pi of the 4 control points, recovered with numpy.linalg.lstsq.

Errors per element, with a = Y.npy and b = this script's output:
    abs error = |a - b|,   rel error = |a - b| / max(|b|, 1)
(relative above one model unit, absolute below, so outputs near zero do not
inflate it). Exit status: 0 if max rel error <= --rtol, 1 if above, 2 for
unusable input.
"""
import argparse
import glob
import os
import sys

import numpy as np


def fail(msg):
    print(f"error: {msg}", file=sys.stderr)
    sys.exit(2)


def load_bin(d, name, count=None):
    """float32 file as float64; count=None takes whatever length it has."""
    path = os.path.join(d, name)
    if not os.path.isfile(path):
        fail(f"{path}: not found")
    a = np.fromfile(path, dtype="<f4")
    if count is not None and a.size != count:
        fail(f"{path}: expected {count * 4} bytes, found {os.path.getsize(path)}")
    if not np.isfinite(a).all():
        fail(f"{path}: non-finite value at index {np.argmin(np.isfinite(a))}")
    return a.astype(np.float64)


def load_network(d):
    """Stats [Xmean, Xstd, Ymean, Ystd], layers [(W[T,out,in], b[T,out])], T."""
    xmean, ymean, hidden = load_bin(d, "Xmean.bin"), load_bin(d, "Ymean.bin"), load_bin(d, "b0_000.bin").size
    stats = [xmean, load_bin(d, "Xstd.bin", xmean.size), ymean, load_bin(d, "Ystd.bin", ymean.size)]
    tables = len(glob.glob(os.path.join(d, "W0_[0-9][0-9][0-9].bin")))
    layers = []
    for l, (rows, cols) in enumerate(((hidden, xmean.size), (hidden, hidden), (ymean.size, hidden))):
        w = [load_bin(d, f"W{l}_{t:03d}.bin", rows * cols).reshape(rows, cols) for t in range(tables)]
        b = [load_bin(d, f"b{l}_{t:03d}.bin", rows) for t in range(tables)]
        layers.append((np.stack(w), np.stack(b)))
    return stats, layers, tables


def spline(a, s):
    """The README's Catmull-Rom formula over control points a[0..3] at s."""
    s = s % 4.0
    k1, mu = int(np.floor(s)) % 4, s - np.floor(s)
    a0, a1, a2, a3 = a[(k1 - 1) % 4], a[k1], a[(k1 + 1) % 4], a[(k1 + 2) % 4]
    return (a1 + mu * (a2 - a0) / 2
            + mu ** 2 * (a0 - 2.5 * a1 + 2 * a2 - 0.5 * a3)
            + mu ** 3 * (1.5 * a1 - 1.5 * a2 + 0.5 * a3 - 0.5 * a0))


def control_points(tabs):
    """Least-squares alpha_0..3 with spline(alpha, 4 i / T) ~ tabs[i]."""
    t = len(tabs)
    basis = np.stack([spline(np.eye(4), 4.0 * i / t) for i in range(t)])
    cp, *_ = np.linalg.lstsq(basis, tabs.reshape(t, -1), rcond=None)
    return cp.reshape((4,) + tabs.shape[1:])


def blend(param, mode, cycles):
    """W or b (tables, or control points for cubic, first) at `cycles` in [0, 1)."""
    if mode == "constant":
        return param[int(np.floor(cycles * len(param))) % len(param)]
    if mode == "linear":
        keys = param[:: len(param) // 10] if len(param) % 10 == 0 else param
        t = cycles * len(keys)
        i, frac = int(np.floor(t)) % len(keys), t - np.floor(t)
        return (1 - frac) * keys[i] + frac * keys[(i + 1) % len(keys)]
    return spline(param, 4.0 * cycles)


def forward(stats, layers, mode, x, phase):
    xmean, xstd, ymean, ystd = stats
    cycles = np.mod(phase, 2 * np.pi) / (2 * np.pi)
    h = (x - xmean) / xstd
    for l, (w, b) in enumerate(layers):
        h = blend(w, mode, cycles) @ h + blend(b, mode, cycles)
        if l < 2:
            h = np.where(h > 0, h, np.expm1(np.minimum(h, 0)))  # ELU
    return h * ystd + ymean


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    for name, text in (("pfnn", "weight directory"), ("inputs", "X.npy"),
                       ("phases", "P.npy"), ("outputs", "Y.npy to check")):
        ap.add_argument(f"--{name}", required=True, help=text)
    ap.add_argument("--gating", required=True, choices=["constant", "linear", "cubic"])
    ap.add_argument("--rtol", type=float, default=1e-5, help="max rel error (default 1e-5)")
    args = ap.parse_args()

    stats, layers, tables = load_network(args.pfnn)
    x, y = np.load(args.inputs).astype(np.float64), np.load(args.outputs).astype(np.float64)
    p = np.load(args.phases).astype(np.float64).reshape(-1)
    n_in, n_out = stats[0].size, stats[2].size
    if tables == 0 or x.ndim != 2 or len(x) == 0 or x.shape[1] != n_in or p.shape != (len(x),) \
            or y.shape != (len(x), n_out):
        fail(f"{tables} tables; inputs {x.shape}, phases {p.shape}, outputs {y.shape}; "
             f"expected tables > 0 and N x {n_in}, N, N x {n_out} with N > 0")
    if args.gating == "cubic":
        layers = [(control_points(w), control_points(b)) for w, b in layers]

    ref = np.stack([forward(stats, layers, args.gating, xi, pi) for xi, pi in zip(x, p)])
    abs_err = np.abs(y - ref)
    rel_err = abs_err / np.maximum(np.abs(ref), 1.0)
    worst = np.unravel_index(np.argmax(rel_err), rel_err.shape)
    ok = rel_err.max() <= args.rtol  # NaN in Y.npy compares False: FAIL
    print(f"{len(x)} samples, {args.gating} gating, {tables} tables: max abs error "
          f"{abs_err.max():.3e}, max rel error {rel_err.max():.3e} (sample {worst[0]}, "
          f"output {worst[1]}), rtol {args.rtol:g}: {'OK' if ok else 'FAIL'}")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
