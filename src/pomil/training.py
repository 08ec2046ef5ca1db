"""What every learner shares: seeding, logging, progress, checkpoints, resume.

A run directory holds::

    checkpoint.pt   latest checkpoint (written atomically; loads weights_only)
    config.json     the run's configuration
    metrics.csv     one row per logged iteration
    tb/             TensorBoard event files
"""

from __future__ import annotations

import csv
import io
import json
import math
import random
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pomil.data import atomic_write
from pomil.errors import PomilError

CHECKPOINT_FORMAT = "pomil-checkpoint"
CHECKPOINT_VERSION = 1


def seed_everything(seed: int) -> torch.Generator:
    """Seed torch's global RNG (network initialisation) and return a generator
    for everything sampled during training, which is passed in explicitly."""
    torch.manual_seed(seed)
    random.seed(seed)
    np.random.seed(seed % 2**32)
    return torch.Generator().manual_seed(seed)


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise PomilError(f"device '{name}' requested but CUDA is not available; use --device cpu")
    device = torch.device(name)
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise PomilError(f"device '{name}' requested but this machine has {torch.cuda.device_count()} CUDA device(s)")
    return device


# ----------------------------------------------------------------- checkpoints
def save_checkpoint(path: str | Path, payload: dict[str, Any]) -> None:
    """Atomically write a checkpoint dict (tensors, numbers, strings, lists, dicts)."""
    payload = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, **payload}
    atomic_write(Path(path), lambda f: torch.save(payload, f))


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load a checkpoint without unpickling arbitrary objects (weights_only=True)."""
    path = Path(path)
    if path.is_dir():
        path = path / "checkpoint.pt"
    if not path.exists():
        raise PomilError(f"{path}: no such checkpoint")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # torch raises many types for foreign/corrupt files
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise PomilError(f"{path}: not a pomil checkpoint ({first[:160]})") from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise PomilError(f"{path}: not a pomil checkpoint (missing 'format: {CHECKPOINT_FORMAT}')")
    if payload.get("version") != CHECKPOINT_VERSION:
        raise PomilError(f"{path}: checkpoint version {payload.get('version')} is not supported (expected {CHECKPOINT_VERSION})")
    return payload


# Settings a resumed run may change: they do not alter what is computed.
RESUMABLE_CHANGES = frozenset({"iterations", "progress", "checkpoint_every", "log_every", "device"})


def check_resume_config(ckpt: dict[str, Any], config: dict[str, Any], path: str | Path) -> None:
    """Refuse to resume a run under a config that would change its results."""
    saved = ckpt.get("config", {})
    changed = sorted(k for k in set(config) | set(saved) if saved.get(k) != config.get(k) and k not in RESUMABLE_CHANGES)
    if changed:
        raise PomilError(f"{path}: cannot resume with a different config (changed: {', '.join(changed)})")


def resume_run(
    ckpt_path: Path, config: dict[str, Any], nets: dict[str, Any], optimizers: dict[str, Any],
    generator: torch.Generator, device: torch.device | str = "cpu",
) -> int:
    """Restore networks, optimisers and RNGs from a run's checkpoint; returns its iteration.

    ``nets`` maps a key of the checkpoint's ``nets`` (or ``policy``) to a module;
    None entries are skipped.
    """
    if not ckpt_path.exists():
        raise PomilError(f"{ckpt_path}: nothing to resume (no checkpoint in {ckpt_path.parent})")
    ckpt = load_checkpoint(ckpt_path, device)
    check_resume_config(ckpt, config, ckpt_path)
    saved_nets = ckpt.get("nets", {"policy": ckpt.get("policy")})
    for k, net in nets.items():
        if net is not None:
            net.load_state_dict(saved_nets[k])
    for k, opt in optimizers.items():
        opt.load_state_dict(ckpt["optimizers"][k])
    restore_rng(ckpt["rng"], generator)
    return int(ckpt["iteration"])


def rng_state(generator: torch.Generator) -> dict[str, torch.Tensor]:
    return {"torch": torch.get_rng_state(), "generator": generator.get_state()}


def restore_rng(state: dict[str, torch.Tensor], generator: torch.Generator) -> None:
    torch.set_rng_state(state["torch"])
    generator.set_state(state["generator"])


# --------------------------------------------------------------------- logging
class RunLogger:
    """Progress bar with the key figures, CSV rows and TensorBoard scalars.

    ``log(iteration, stats)`` writes one CSV row and the scalars; ``update``
    advances the bar.  On resume the CSV keeps only rows up to the iteration
    the checkpoint was written at, so the log reads as one continuous run.
    """

    def __init__(
        self, run_dir: str | Path, total: int, start: int = 0, progress: bool = True,
        desc: str = "train", key_stats: tuple[str, ...] = (),
    ) -> None:
        from torch.utils.tensorboard import SummaryWriter
        from tqdm.auto import tqdm

        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.csv_path = self.run_dir / "metrics.csv"
        self.key_stats = key_stats
        self._rows: list[dict[str, Any]] = []
        if start > 0 and self.csv_path.exists():
            with open(self.csv_path, newline="") as f:
                self._rows = [r for r in csv.DictReader(f) if int(r["iteration"]) <= start]
        elif self.csv_path.exists():
            self.csv_path.unlink()
        self._fields: list[str] = list(self._rows[0].keys()) if self._rows else []
        self._last_flush = time.monotonic()
        self.writer = SummaryWriter(str(self.run_dir / "tb"), purge_step=start if start > 0 else None)
        self.bar = tqdm(
            total=total, initial=start, desc=desc, disable=not progress, dynamic_ncols=True,
            mininterval=0.5 if sys.stderr.isatty() else 5.0, file=sys.stderr,
        )

    def log(self, iteration: int, stats: dict[str, float]) -> None:
        row = {"iteration": iteration, **{k: float(v) for k, v in stats.items()}}
        if not self._fields:
            self._fields = list(row.keys())
        for k in row:
            if k not in self._fields:
                self._fields.append(k)
        self._rows.append(row)
        for k, v in stats.items():
            if math.isfinite(float(v)):
                self.writer.add_scalar(k, float(v), iteration)
        if time.monotonic() - self._last_flush > 10.0:  # keep metrics.csv current on long runs
            self.flush()
        shown = {k.split("/")[-1]: f"{float(stats[k]):.4g}" for k in self.key_stats if k in stats}
        self.bar.set_postfix(shown, refresh=False)

    def update(self, n: int = 1) -> None:
        self.bar.update(n)

    def flush(self) -> None:
        """Rewrite the CSV atomically (cheap: one row per logged iteration)."""
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=self._fields, restval="")
        w.writeheader()
        w.writerows(self._rows)
        data = buf.getvalue().encode()
        atomic_write(self.csv_path, lambda f: f.write(data))
        self.writer.flush()
        self._last_flush = time.monotonic()

    def close(self) -> None:
        self.flush()
        self.writer.close()
        self.bar.close()


def write_json(path: str | Path, obj: Any) -> None:
    data = (json.dumps(obj, indent=2, sort_keys=False) + "\n").encode()
    atomic_write(Path(path), lambda f: f.write(data))
