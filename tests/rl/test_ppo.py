import pytest
import torch

from pomil.rl.ppo import normalize, ppo_loss


def test_ppo_loss_without_clipping_is_the_plain_surrogate():
    old = torch.zeros(2)
    new = torch.log(torch.tensor([1.1, 0.95]))  # ratios inside [0.8, 1.2]
    adv = torch.tensor([1.0, -2.0])
    zero = torch.zeros(2)
    loss, stats = ppo_loss(new_logp=new, old_logp=old, advantages=adv, new_values=zero, old_values=zero, returns=zero,
             entropy=zero, clip=0.2, vf_coef=0.0)
    assert loss.item() == pytest.approx(-(1.1 * 1.0 + 0.95 * -2.0) / 2)
    assert stats["ppo/clip_fraction"] == 0.0


def test_ppo_loss_clips_large_ratios():
    old = torch.zeros(2)
    new = torch.log(torch.tensor([1.5, 0.5]))
    adv = torch.tensor([1.0, -1.0])
    zero = torch.zeros(2)
    loss, stats = ppo_loss(new_logp=new, old_logp=old, advantages=adv, new_values=zero, old_values=zero, returns=zero,
             entropy=zero, clip=0.2, vf_coef=0.0)
    # min(1.5*1, 1.2*1) = 1.2; min(0.5*-1, 0.8*-1) = -0.8
    assert loss.item() == pytest.approx(-(1.2 - 0.8) / 2)
    assert stats["ppo/clip_fraction"] == 1.0
    # no gradient flows through a clipped term
    new = new.clone().requires_grad_(True)
    ppo_loss(new_logp=new, old_logp=old, advantages=adv, new_values=zero, old_values=zero, returns=zero,
             entropy=zero, clip=0.2, vf_coef=0.0)[0].backward()
    assert new.grad.tolist() == [0.0, 0.0]


def test_value_clipping_and_entropy_and_mask():
    z = torch.zeros(3)
    new_v = torch.tensor([2.0, 0.0, 100.0])
    old_v = torch.tensor([0.0, 0.0, 0.0])
    ret = torch.tensor([1.0, 1.0, 0.0])
    ent = torch.tensor([1.0, 3.0, 100.0])
    mask = torch.tensor([True, True, False])
    loss, stats = ppo_loss(new_logp=z, old_logp=z, advantages=z, new_values=new_v, old_values=old_v, returns=ret,
                           entropy=ent, mask=mask, value_clip=0.5, vf_coef=1.0, ent_coef=0.1)
    # entry 0: max((2-1)^2, (0.5-1)^2) = 1; entry 1: max(1, 1) = 1 -> 0.5 * mean = 0.5
    assert stats["ppo/value_loss"] == pytest.approx(0.5)
    assert stats["ppo/entropy"] == pytest.approx(2.0)
    assert loss.item() == pytest.approx(0.5 - 0.2)


def test_normalize_with_mask():
    x = normalize(torch.tensor([1.0, 3.0, 1000.0]), torch.tensor([True, True, False]))
    assert x[:2].tolist() == pytest.approx([-1.0, 1.0], abs=1e-6)


def test_ppo_loss_refuses_positional_arguments():
    z = torch.zeros(2)
    with pytest.raises(TypeError):
        ppo_loss(z, z, z, z, z, z, z)
