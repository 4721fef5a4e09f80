"""`--weight-noise`: the int8-sized perturbation of training moves each weight by at most
half an int8 step (its row's largest magnitude / 127) and comes off bit for bit. Needs
PyTorch (the training environment, tools/omg/requirements-train.txt); skipped without it."""

import pytest

torch = pytest.importorskip("torch")

from tools.omg.train.core import int8_noise, restore, weight_matrices  # noqa: E402
from tools.omg.train.model import OMG  # noqa: E402

SLICES = {"phase": (0, 8), "pose": (8, 20), "cost": (20, 44), "target": (44, 80)}


@pytest.mark.parametrize("variant", ["FE", "RBF-CAT"])
def test_noise_is_within_half_a_step_per_row_and_comes_off_exactly(variant):
    torch.manual_seed(0)
    model = OMG(SLICES, variant=variant, size="tiny")
    before = [w.detach().clone() for w, _ in weight_matrices(model)]
    # every layer of the four MLPs and the three expert stacks
    assert len(before) == 4 * 3 + 3
    gen = torch.Generator().manual_seed(1)
    clean = int8_noise(model, 1.0, gen)
    for (w, axis), w0 in zip(weight_matrices(model), before):
        step = w0.abs().amax(dim=axis, keepdim=True) / 127.0
        moved = (w.detach() - w0).abs()
        assert torch.all(moved <= step / 2 * (1 + 1e-5))
        assert moved.max() > 0
    restore(clean)
    for (w, _), w0 in zip(weight_matrices(model), before):
        assert torch.equal(w.detach(), w0)
