"""Synthetic reaching-motion data for the OMG model (issue 10). See README.md."""

import os as _os

# Single-threaded BLAS unless the caller says otherwise (the machine's cores are shared;
# this only takes effect when the package is imported before NumPy loads its BLAS).
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
