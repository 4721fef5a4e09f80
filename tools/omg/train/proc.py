"""What the fine-tuning tools share without PyTorch: qat's defaults (``tools.omg.train.choose``
leaves them out of the commands it builds, so it must know them but cannot import qat, which
needs PyTorch) and running the project's binaries."""

from __future__ import annotations

import subprocess

QAT_LR = 2e-4
EXPORTER = "target/release/exporter"


def run(cmd: list) -> None:
    """Runs ``cmd``; on failure stops with one line naming the command and what it said."""
    r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, cmd))}: {r.stderr.strip() or r.stdout.strip()}")
