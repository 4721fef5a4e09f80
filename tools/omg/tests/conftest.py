import os
import sys
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

# Make `tools.omg` importable however pytest is started (repo root on sys.path).
ROOT = Path(__file__).resolve().parents[3]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from tools.omg import features  # noqa: E402
from tools.omg.ik import IKParams  # noqa: E402
from tools.omg.rigs import build_rig  # noqa: E402
from tools.omg.simulate import simulate  # noqa: E402
from tools.omg.targets import plan_clips  # noqa: E402


@pytest.fixture(scope="session")
def sample_plans():
    """12 clips spread over the plan: both rotation settings, 1-3 repetitions, both radii."""
    return plan_clips(0)[::20]


@pytest.fixture(scope="session")
def sample_data(sample_plans):
    """{rig: (rig, frames, sim)} for two rigs of different sizes."""
    out = {}
    for name in ("R1", "R4"):
        rig = build_rig(name)
        sim = simulate(rig, sample_plans, IKParams())
        frames = features.assemble(rig, sim)
        out[name] = (rig, frames, sim)
    return out
