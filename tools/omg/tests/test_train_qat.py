"""Quantisation-aware training's rounding (``core.grid_round``): every weight matrix named in
the grid lands on the exporter's int8 grid (a row's scale from its largest ``|w / u|``, an
expert stack's experts sharing their output rows) and comes off bit for bit. Needs PyTorch
(tools/omg/requirements-train.txt); skipped without it."""

import pytest

torch = pytest.importorskip("torch")

from tools.omg.train.core import grid_round, restore  # noqa: E402
from tools.omg.train.model import OMG  # noqa: E402

SLICES = {"phase": (0, 8), "pose": (8, 20), "cost": (20, 44), "target": (44, 80)}


def column_scales(model, gen):
    """Powers of two per input column, as the exporter's row formats are."""
    grid = {}
    for name, t in model.named_tensors().items():
        if name.endswith(".w"):
            cols = t.shape[1]
        elif name.startswith("experts.w"):
            cols = t.shape[1]
        else:
            continue
        grid[name] = [float(2 ** int(e)) for e in torch.randint(8, 14, (cols,), generator=gen)]
    return grid


@pytest.mark.parametrize("variant", ["FE", "RBF-CAT"])
def test_grid_round_puts_every_weight_on_its_rows_grid_and_comes_off_exactly(variant):
    torch.manual_seed(0)
    model = OMG(SLICES, variant=variant, size="tiny")
    gen = torch.Generator().manual_seed(2)
    grid = column_scales(model, gen)
    assert len(grid) == 4 * 3 + 3
    before = {k: v.detach().clone() for k, v in model.named_tensors().items()}
    clean = grid_round(model, grid, 127.0)
    after = model.named_tensors()
    for name, u in grid.items():
        w = after[name].detach().double()
        u = torch.tensor(u, dtype=torch.float64)
        if name.startswith("experts.w"):  # (k, in, out): a row is an output, over every expert
            e = w / u[None, :, None]
            most = e.abs().amax(dim=(0, 1), keepdim=True)
        else:
            e = w / u[None, :]
            most = e.abs().amax(dim=1, keepdim=True)
        steps = e / most * 127.0
        assert torch.allclose(steps, steps.round(), atol=1e-3), name
        assert torch.allclose(steps.abs().amax(), torch.tensor(127.0, dtype=torch.float64)), name
        # each weight at most half its step from where it was (float32 arithmetic aside)
        step = (u[None, :, None] if e.dim() == 3 else u[None, :]) * most / 127.0
        moved = (w - before[name].double()).abs()
        assert torch.all(moved <= step / 2 * (1 + 1e-4) + 1e-9), name
        assert moved.max() > 0, name
    for name, t in after.items():
        if name not in grid:
            assert torch.equal(t.detach(), before[name]), name
    restore(clean)
    for name, t in model.named_tensors().items():
        assert torch.equal(t.detach(), before[name]), name
