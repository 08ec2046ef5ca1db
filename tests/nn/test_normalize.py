import numpy as np
import torch

from pomil.nn.normalize import RunningNorm
from pomil.rl.storage import Rollout


def test_running_norm_matches_numpy_over_batches():
    rng = np.random.default_rng(0)
    data = rng.normal(3.0, 2.0, (1000, 4))
    norm = RunningNorm(4)
    for chunk in np.array_split(data, 7):
        norm.update(torch.as_tensor(chunk))
    np.testing.assert_allclose(norm.mean.numpy(), data.mean(0), rtol=1e-6)
    np.testing.assert_allclose(norm.var.numpy(), data.var(0), rtol=1e-4)
    y = norm(torch.as_tensor(data, dtype=torch.float32))
    np.testing.assert_allclose(y.mean(0).numpy(), 0.0, atol=1e-4)


def test_step_batches_visit_every_step_once():
    T, N = 5, 3
    ids = torch.arange(T * N, dtype=torch.float32).view(T, N)
    z = torch.zeros(T, N)
    roll = Rollout(observations=ids.unsqueeze(-1), actions=z.unsqueeze(-1), prev_actions=z.unsqueeze(-1),
                   starts=torch.zeros(T, N, dtype=torch.bool), codes=torch.zeros(T, N, 0), log_probs=z, values=z,
                   terminated=z.bool(), truncated=z.bool(), mask=torch.ones(T, N, dtype=torch.bool),
                   h0_policy=torch.zeros(N, 0), h0_value=torch.zeros(N, 0))
    seen = torch.cat([b.observations.flatten() for b in roll.step_batches(4, torch.Generator().manual_seed(0))])
    assert sorted(seen.tolist()) == list(range(T * N))
