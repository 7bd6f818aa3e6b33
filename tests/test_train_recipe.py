"""The CPU training step's shortcut (models.train.recipe_losses_winner) has the recipe's gradient: with
the same latents, the best-of-K term's gradient flows through each window's best latent alone, so with
eps = 0 it is the full recipe's to float rounding. Needs torch and ../shared/mocap."""
import numpy as np
import pytest

from motion import dataset as ds


@pytest.fixture(scope="module")
def batch(torch, mocap):
    from models.train import to_t
    val = ds.build(mocap, "val")
    rng = np.random.default_rng(2)
    return to_t(ds.make_batch(val, rng.choice(ds.window_starts(val, 30), 12), 30, rng))


def gradients(torch, model, terms):
    model.zero_grad()
    (terms["mse"] + terms["variety"]).backward()
    return torch.cat([p.grad.flatten() for p in model.parameters() if p.grad is not None])


def test_the_winner_only_gradient_is_the_recipes_best_of_k_gradient(torch, batch):
    from models import train as tr
    from models.nets import CVAE
    torch.manual_seed(0)
    model = CVAE(hidden=32)
    model.norm.fit(batch["features"])
    torch.manual_seed(11)
    full = tr.recipe_losses(model, batch, 6, eps=0.0)
    g_full = gradients(torch, model, full)
    torch.manual_seed(11)
    fast = tr.recipe_losses_winner(model, batch, 6, eps=0.0)
    g_fast = gradients(torch, model, fast)
    assert fast["variety"].item() == pytest.approx(full["variety"].item(), rel=1e-5)
    assert fast["mse"].item() == pytest.approx(full["mse"].item(), rel=1e-6)
    np.testing.assert_allclose(g_fast.numpy(), g_full.numpy(), rtol=1e-3, atol=1e-6 * g_full.abs().max().item())
