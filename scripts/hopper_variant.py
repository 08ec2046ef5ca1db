"""One exploratory InfoGAIL-POMDP run on Hopper: the library defaults plus overrides.

    .venv/bin/python scripts/hopper_variant.py OUT SEED DEVICE '{"bc_weight": 10}'

Runs ``train_adversarial`` with ``AdversarialConfig``'s defaults (the recipe the
runs below led to), 30 iterations on ``data/hopper-paper.npz``, a log row every iteration and the given
JSON overrides (any ``AdversarialConfig`` key).  The runs in
``results/hopper/exploration.json`` ("device_runs") were made this way.
"""

import json
import sys

from pomil.algos.adversarial import AdversarialConfig, train_adversarial
from pomil.config import from_dict

if __name__ == "__main__":
    if len(sys.argv) != 5:
        sys.exit(__doc__.strip().splitlines()[2].strip())
    out, seed, device, overrides = sys.argv[1], int(sys.argv[2]), sys.argv[3], json.loads(sys.argv[4])
    values = {"learner": "infogail-pomdp", "demos": "data/hopper-paper.npz", "out": out,
              "iterations": 30, "seed": seed, "device": device, "progress": False, "log_every": 1, **overrides}
    train_adversarial(from_dict(AdversarialConfig, values, "hopper_variant"))
