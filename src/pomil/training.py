"""What every learner shares: the run loop (:class:`RunLoop`: seeding, the run directory's
lock, config.json, resume, the cadence of evaluation, logging and checkpoints, and the one
checkpoint schema, :meth:`RunLoop.state`), and the pieces it is made of: logging and
progress, atomic checkpoints, resume, the divergence guard and the lock.

A run directory holds::

    checkpoint.pt   latest checkpoint (written atomically; loads weights_only; never NaN/inf)
    config.json     the run's configuration
    metrics.csv     one row per logged iteration
    tb/             TensorBoard event files
    run.lock        while a run writes: its pid, host and start time (one writer at a time)
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import io
import json
import math
import os
import random
import shutil
import socket
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pomil.config import saved_config, to_dict
from pomil.data import atomic_write
from pomil.errors import DivergenceError, PomilError, RunBusyError

CHECKPOINT_FORMAT = "pomil-checkpoint"
CHECKPOINT_VERSION = 1


def seed_everything(seed: int) -> torch.Generator:
    """Seed torch's global RNG (network initialisation) and return a generator
    for everything sampled during training, which is passed in explicitly."""
    torch.manual_seed(seed)
    random.seed(seed)
    np.random.seed(seed % 2**32)
    return torch.Generator().manual_seed(seed)


def resolve_device(name: str | torch.device) -> torch.device:
    name = str(name)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise PomilError(f"device '{name}' requested but CUDA is not available; use --device cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        raise PomilError(f"device {name!r}: expected cpu, cuda, cuda:N, mps or auto") from None
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise PomilError(f"device '{name}' requested but this machine has {torch.cuda.device_count()} CUDA device(s)")
    return device


def native_bfloat16(device: torch.device) -> bool:
    """Whether ``device`` computes bfloat16 matrix products natively (a CPU with AVX512-BF16 or
    AMX, as oneDNN reports it; a GPU that supports it): elsewhere they are emulated, and slower
    than float32."""
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    return (device.type == "cpu" and torch.backends.mkldnn.is_available()
            and bool(torch.ops.mkldnn._is_mkldnn_bf16_supported()))


def precision_context(precision: str, device: torch.device) -> AbstractContextManager[None]:
    """What the updates' network passes run in: with ``bfloat16``, ``torch.autocast`` in bfloat16
    (the matrix products and the recurrent cores' gates round to bfloat16; the networks' outputs,
    losses, gradients and weights stay float32, see ``pomil.nn.heads``); with ``float32``, nothing
    (bit for bit the computation without it).  Enter it once per optimiser step, around the
    forward pass: autocast caches each weight's bfloat16 copy until the context ends, so a context
    around several steps (a phase, the warm start) would go on computing with the weights of its
    first step.  Its end clears that cache even inside an enclosing autocast (whose own end would
    be the first to clear it otherwise)."""
    if precision == "float32":
        return nullcontext()
    return _bfloat16_autocast(device.type)


@contextmanager
def _bfloat16_autocast(device_type: str) -> Iterator[None]:
    try:
        with torch.autocast(device_type, dtype=torch.bfloat16):
            yield
    finally:
        torch.clear_autocast_cache()


# ----------------------------------------------------------------- checkpoints
def first_nonfinite(obj: Any, where: str = "") -> str | None:
    """Key path (``nets.value.mlp.0.weight``) of the first floating tensor or float in a
    nested dict / list that holds NaN or inf; None when every one is finite."""
    if isinstance(obj, torch.Tensor):
        return where if obj.is_floating_point() and not bool(torch.isfinite(obj).all()) else None
    if isinstance(obj, float):
        return None if math.isfinite(obj) else where
    if isinstance(obj, dict):
        items: Iterable = obj.items()
    elif isinstance(obj, (list, tuple)):
        items = enumerate(obj)
    else:
        return None
    for k, v in items:
        bad = first_nonfinite(v, f"{where}.{k}" if where else str(k))
        if bad is not None:
            return bad
    return None


def save_checkpoint(path: str | Path, payload: dict[str, Any]) -> None:
    """Atomically write a checkpoint dict (tensors, numbers, strings, lists, dicts).

    A payload holding NaN or inf is never written (the divergence guard stops a
    run before this; this is the last line): the previous checkpoint stays."""
    bad = first_nonfinite({k: v for k, v in payload.items() if k != "config"})
    if bad is not None:
        raise DivergenceError(f"{path}: not writing a checkpoint whose '{bad}' holds NaN/inf "
                              f"(iteration {payload.get('iteration', '?')}); the previous checkpoint is unchanged")
    payload = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, **payload}
    atomic_write(Path(path), lambda f: torch.save(payload, f))


def save_run_checkpoint(path: str | Path, logger: RunLogger, guard: DivergenceGuard, *, iteration: int,
                        payload: dict[str, Any]) -> None:
    """A run's checkpoint of ``iteration``: the metrics flushed first, so that a resumed run's log
    reads as one; the guard told, so that a later divergence names it."""
    logger.flush()
    save_checkpoint(path, {"iteration": iteration, **payload})
    guard.saved(iteration)


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
    if not isinstance(payload, dict) or not isinstance(payload.get("format"),
                                                       str) or payload["format"] != CHECKPOINT_FORMAT:
        raise PomilError(f"{path}: not a pomil checkpoint (missing 'format: {CHECKPOINT_FORMAT}')")
    if type(payload.get("version")) is not int or payload["version"] != CHECKPOINT_VERSION:
        raise PomilError(f"{path}: checkpoint version {payload.get('version')} is not supported (expected "
                         f"{CHECKPOINT_VERSION})")
    bad = first_nonfinite({k: v for k, v in payload.items() if k != "config"})
    if bad is not None:
        raise PomilError(f"{path}: '{bad}' holds NaN/inf (the run that wrote it diverged); "
                         "use an earlier checkpoint or train again with a lower learning rate")
    return payload


RUN_FILES = ("checkpoint.pt", "metrics.csv", "config.json", "tb")
"""What a run writes into its directory: a directory holding any of them holds a run."""

# Settings a resumed run may change: they do not alter what is computed (``out``: a run
# directory may be moved), except the learning rates, which may be lowered to continue
# a run that diverged.
RESUMABLE_CHANGES = frozenset({"iterations", "progress", "checkpoint_every", "log_every", "device", "out", "overwrite",
                               "lr", "lr_value", "lr_critic", "lr_posterior", "warm_start_lr"})


def check_resume_config(ckpt: dict[str, Any], config: dict[str, Any], path: str | Path,
                        config_class: type | None = None) -> None:
    """Refuse to resume a run under a config that would change its results.

    With ``config_class``, a checkpoint of an earlier version has its config read as this
    version writes it (:func:`pomil.config.saved_config`: renamed keys, new keys at their defaults)."""
    saved = ckpt.get("config", {})
    if not isinstance(saved, dict):
        raise TypeError("config")
    if config_class is not None:
        saved = saved_config(config_class, saved)
    changed = sorted(k for k in set(config) | set(saved)
                     if saved.get(k) != config.get(k) and k not in RESUMABLE_CHANGES)
    if changed:
        raise PomilError(f"{path}: cannot resume with a different config (changed: {', '.join(changed)})")


@dataclass(frozen=True)
class RunStart:
    """Where a run starts: iteration 0 and no environment steps, or a checkpoint's."""

    iteration: int = 0
    env_steps: int = 0


def resume_run(
    ckpt_path: Path, config: dict[str, Any], nets: dict[str, Any], *, optimizers: dict[str, Any],
    generator: torch.Generator, device: torch.device | str = "cpu", config_class: type | None = None,
    carried: dict[str, Any] | None = None,
) -> RunStart:
    """Restore networks, optimisers, RNGs and carried state from a run's checkpoint; returns its
    iteration and environment-step count.

    ``nets`` maps a key of the checkpoint's ``nets`` (or ``policy``) to a module;
    None entries are skipped.  The optimisers keep the hyperparameters they were built
    with (the run's config), so that a resumed run may lower its learning rates.  ``carried``
    maps a key of the checkpoint's ``carried`` to an object with ``load_state_dict`` (what a
    running process holds beside its networks: the environment's generators, a code assignment);
    a checkpoint written before pomil kept it resumes with that state fresh, with a note (the
    run then goes on, but not bit for bit as it would have).  A config whose ``iterations`` is
    below the checkpoint's iteration is refused.
    """
    if not ckpt_path.exists():
        raise PomilError(f"{ckpt_path}: nothing to resume (no checkpoint in {ckpt_path.parent})")
    ckpt = load_checkpoint(ckpt_path, device)
    try:
        check_resume_config(ckpt, config, ckpt_path, config_class)
    except (TypeError, ValueError, RuntimeError, AttributeError):
        raise PomilError(f"{ckpt_path}: cannot resume from this checkpoint (its 'config' is damaged)") from None
    done = ckpt.get("iteration")
    if not isinstance(done, int) or isinstance(done, bool) or done < 0:
        raise PomilError(f"{ckpt_path}: checkpoint has no usable 'iteration' (got {done!r})")
    if config.get("iterations", done) < done:
        raise PomilError(f"{ckpt_path}: the checkpoint is at iteration {done}, past --iterations "
                         f"{config['iterations']}; "
                         f"nothing to resume (pass --iterations above {done} to continue; the checkpoint is unchanged)")
    try:
        saved_nets = ckpt.get("nets", {"policy": ckpt.get("policy")})
        for k, net in nets.items():
            if net is not None:
                net.load_state_dict(saved_nets[k])
        for k, opt in optimizers.items():
            # Hyperparameters come from the run's config and code, not from the file: the
            # learning rates may have been lowered, and a damaged file cannot break the next step.
            hypers = [{key: v for key, v in g.items() if key != "params"} for g in opt.param_groups]
            opt.load_state_dict(ckpt["optimizers"][k])
            check_optimizer_state(opt)
            for g, h in zip(opt.param_groups, hypers, strict=True):
                for key in set(g) - set(h) - {"params"}:
                    del g[key]
                g.update(h)
        restore_rng(ckpt["rng"], generator)
        restore_carried(ckpt_path, ckpt.get("carried"), carried or {})
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as err:
        first = (str(err).strip().splitlines() or [type(err).__name__])[0][:160]
        raise PomilError(f"{ckpt_path}: cannot resume from this checkpoint ({type(err).__name__}: {first})") from None
    steps = ckpt.get("env_steps", 0)
    return RunStart(done, int(steps) if isinstance(steps, (int, float)) and math.isfinite(steps) else 0)


def restore_carried(ckpt_path: Path, saved: Any, carried: dict[str, Any]) -> None:
    """Load each object of ``carried`` from the checkpoint's ``carried`` entry of its name (see :func:`resume_run`)."""
    if not carried:
        return
    if saved is None:
        print(f"pomil: note: {ckpt_path} keeps no state beside the networks ({', '.join(carried)}): resuming with "
              "it fresh, so this run goes on close to, not exactly as, the run uninterrupted", file=sys.stderr)
        return
    if not isinstance(saved, dict):
        raise TypeError("'carried' is not a dict")
    for name, obj in carried.items():
        if name not in saved:  # kept by a later version than the one that wrote the checkpoint
            print(f"pomil: note: {ckpt_path} keeps no {name} state: resuming with it fresh", file=sys.stderr)
            continue
        obj.load_state_dict(saved[name])


def check_optimizer_state(opt: torch.optim.Optimizer) -> None:
    """ValueError unless every parameter's state has the same keys, each a tensor of the
    parameter's shape, and ``step`` is one number >= 1: load_state_dict takes a damaged
    state, and the next step would fail."""
    states = [(p, opt.state[p]) for group in opt.param_groups for p in group["params"] if p in opt.state]
    keys = set().union(*(s.keys() for _, s in states)) if states else set()
    for p, state in states:
        if set(state) != keys:
            raise ValueError(f"optimizer state keys {sorted(state)}, expected {sorted(keys)}")
        for key, v in state.items():
            if key == "step":  # steps taken: a number >= 1 (Adam divides by 1 - beta ** step)
                n = v.item() if isinstance(v, torch.Tensor) and v.numel() == 1 and not v.is_complex() else v
                if isinstance(n, bool) or not isinstance(n, (int, float)) or not 1 <= n < float("inf"):
                    raise ValueError(f"optimizer 'step' is {v!r:.60}")
            elif not isinstance(v, torch.Tensor) or v.shape != p.shape:
                raise ValueError(f"optimizer state '{key}' is not a tensor of its parameter's shape {tuple(p.shape)}")


def rng_state(generator: torch.Generator, penalty: torch.Generator) -> dict[str, torch.Tensor]:
    """A checkpoint's ``rng``: ``torch``, the penalty generator's state (see :meth:`RunLoop.start`); ``generator``."""
    return {"torch": penalty.get_state(), "generator": generator.get_state()}


def restore_rng(state: dict[str, torch.Tensor], generator: torch.Generator) -> None:
    torch.set_rng_state(state["torch"])
    generator.set_state(state["generator"])


# ------------------------------------------------------------ divergence guard
class DivergenceGuard:
    """Stops a run at the first NaN or inf in a loss, gradient, parameter or reward.

    Every learner's loop calls the same checks, in the iteration where the value
    appears and before any checkpoint of that iteration, so a diverged run never
    writes a non-finite checkpoint and its last good one stays for ``--resume``.
    The checks only read values: a run that does not diverge computes exactly
    what it computed without them.

    ``hints`` maps a quantity's first word (``critic``, ``policy``, ``reward``,
    ...) to the option that most likely made it diverge, e.g.
    ``{"critic": "--lr-critic (now 10000.0)"}``; ``on_stop`` (flushing the
    metrics, say) runs before the error is raised.
    """

    def __init__(self, ckpt_path: Path, hints: dict[str, str], saved_iteration: int = 0,
                 on_stop: Callable[[], None] | None = None) -> None:
        self.ckpt_path = Path(ckpt_path)
        self.hints = hints
        self.saved_iteration = saved_iteration  # the last checkpoint's iteration (0: none yet)
        self.on_stop = on_stop

    def saved(self, iteration: int) -> None:
        """Record that a checkpoint of ``iteration`` was written."""
        self.saved_iteration = iteration

    def value(self, step: int | str, quantity: str, x: float | torch.Tensor) -> None:
        """A scalar or tensor (loss, reward, gradient norm) must be finite everywhere."""
        if isinstance(x, torch.Tensor):
            self._tensor(step, quantity, x.detach())
        elif not math.isfinite(x):
            self.stop(step, quantity, x)

    def grads(self, step: int | str, name: str, params: Iterable[torch.nn.Parameter]) -> None:
        """Every gradient of ``params`` (after backward, before the optimiser step) must be finite."""
        grads = [p.grad for p in params if p.grad is not None]
        if all_finite(grads):
            return
        for g in grads:
            self._tensor(step, f"{name} gradient", g)

    def params(self, step: int | str, nets: dict[str, torch.nn.Module | None]) -> None:
        """Every parameter and buffer of every net must be finite."""
        named = [(f"{name} parameter '{key}'", t) for name, net in nets.items() if net is not None
                 for key, t in net.state_dict().items() if t.is_floating_point()]
        if all_finite([t for _, t in named]):
            return
        for quantity, t in named:
            self._tensor(step, quantity, t)

    def _tensor(self, step: int | str, quantity: str, t: torch.Tensor) -> None:
        if not bool(torch.isfinite(t).all()):
            self.stop(step, quantity, t[~torch.isfinite(t)].flatten()[0].item())

    def stop(self, step: int | str, quantity: str, bad: float) -> None:
        if self.on_stop is not None:
            self.on_stop()
        where = f"iteration {step}" if isinstance(step, int) else step
        hint = self.hints.get(quantity.split()[0], "")
        lower = ("a lower " + hint.split(" (")[0]) if hint.count("(now") == 1 else "lower learning rates"
        if self.saved_iteration > 0 and self.ckpt_path.exists():
            after = (f"{self.ckpt_path} (iteration {self.saved_iteration}) is unchanged: "
                     f"continue it with --resume and {lower}")
        else:
            after = f"no checkpoint of this run was written: start it again with {lower}"
        raise DivergenceError(f"{where}: {quantity} is {bad} (the run diverged); "
                              f"{'try a lower ' + hint + '; ' if hint else ''}{after}")


def all_finite(tensors: list[torch.Tensor]) -> bool:
    """True when every element of the floating ``tensors`` is surely finite: one fused norm per tensor (a NaN or
    inf element makes its norm NaN or inf).  False asks for the exact check, element by element: a norm can also
    overflow on finite values."""
    floats = [t.detach() for t in tensors if t.is_floating_point()]
    if not floats:
        return True
    try:
        return bool(torch.isfinite(torch.stack([n.float() for n in torch._foreach_norm(floats)])).all())
    except (RuntimeError, TypeError):  # tensors that one fused call cannot take together
        return False


def lr_hint(config: Any, *fields: str) -> str:
    """``--lr-value (now 0.0005) or --lr-critic (now 1e+04)``: the flags of config fields and their values."""
    flags = [f"--{f.replace('_', '-')} (now {getattr(config, f):g})" for f in fields]
    return " or ".join([", ".join(flags[:-1]), flags[-1]] if len(flags) > 1 else flags)


# ------------------------------------------------------------------------ lock
class RunLock:
    """One writer per run directory: ``run.lock``, locked (flock) while a run writes.

    A second run into the same directory is refused with the holder's pid, host
    and start time.  The kernel drops the lock when its process ends, however
    it ends, so a lock file left by a killed run (its process gone) is stale:
    the next run into the directory takes it over.  That run may be a
    ``--resume`` (which continues from the killed run's last checkpoint) or an
    ``--overwrite`` (which starts over, as it would in a finished run's directory);
    either way a note says so.  Used as ``with RunLock(dir) as lock: ...
    lock.acquire(resume)``: acquired when the run is about to write, released
    (and the file removed) when the block ends.
    """

    def __init__(self, run_dir: str | Path) -> None:
        self.path = Path(run_dir) / "run.lock"
        self._fd: int | None = None

    def __enter__(self) -> RunLock:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.release()

    def acquire(self, resume: bool = False) -> None:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            while True:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    holder = self._read(fd)
                    os.close(fd)
                    raise RunBusyError(
                        f"{self.path.parent}: in use by another run (pid {holder.get('pid', '?')} on "
                        f"{holder.get('host', '?')}, since {holder.get('since', '?')}; lock {self.path}): "
                        "wait for it to end, or choose another --out") from None
                try:  # the previous holder may have removed the file between our open and flock
                    same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
                except FileNotFoundError:
                    same = False
                if same:
                    break
                os.close(fd)
            previous = self._read(fd)
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                                      "since": time.strftime("%Y-%m-%d %H:%M:%S")}).encode(), 0)
        except OSError as err:
            raise PomilError(f"{self.path.parent}: cannot write to the run directory ({err.strerror or err})") from None
        self._fd = fd
        if previous:
            what = ("continuing from its last checkpoint" if resume else
                    "starting over (--resume would continue from its last checkpoint)")
            print(f"pomil: note: {self.path} was left by pid {previous.get('pid', '?')} on "
                  f"{previous.get('host', '?')}, "
                  f"which is no longer running; taking it over and {what}", file=sys.stderr)

    @staticmethod
    def _read(fd: int) -> dict[str, Any]:
        try:
            data = json.loads(os.pread(fd, 4096, 0) or b"{}")
        except (ValueError, OSError):
            return {"pid": "?"}
        return data if isinstance(data, dict) else {"pid": "?"}

    def release(self) -> None:
        if self._fd is None:
            return
        with contextlib.suppress(OSError):
            os.unlink(self.path)
        os.close(self._fd)  # closing drops the flock
        self._fd = None


# --------------------------------------------------------------------- logging
class RunLogger:
    """Progress bar with the key figures, CSV rows and TensorBoard scalars.

    ``log(iteration, stats)`` writes one CSV row and the scalars; ``update``
    advances the bar.  On resume (``start`` > 0, or ``resume``: a run resumed at iteration 0) the CSV
    keeps only rows up to the iteration the checkpoint was written at, so the log reads as one continuous run.
    """

    def __init__(
        self, run_dir: str | Path, total: int, start: int = 0, progress: bool = True,
        desc: str = "train", key_stats: tuple[str, ...] = (), resume: bool = False,
    ) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.csv_path = self.run_dir / "metrics.csv"
        self.key_stats = key_stats
        self._rows: list[dict[str, Any]] = []
        if (start > 0 or resume) and self.csv_path.exists():
            with open(self.csv_path, newline="") as f:
                self._rows = [r for r in csv.DictReader(f) if int(r["iteration"]) <= start]
        elif self.csv_path.exists():
            self.csv_path.unlink()
        self._fields: list[str] = list(self._rows[0].keys()) if self._rows else []
        self._last_flush = time.monotonic()
        self.writer = SummaryWriter(str(self.run_dir / "tb"), purge_step=start if start > 0 else None)
        self.bar = progress_bar(total, desc, progress, initial=start)

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


def progress_bar(total: int, desc: str, enabled: bool, initial: int = 0) -> Any:
    """A tqdm bar on stderr, the run loop's and that of a long step before or beside it (the warm start, the
    posterior's warm-up): drawn every 0.5 s on a terminal, every 5 s otherwise."""
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, desc=desc, disable=not enabled, dynamic_ncols=True, file=sys.stderr,
                mininterval=0.5 if sys.stderr.isatty() else 5.0)


class EpisodeProgress:
    """Moves ``bar`` (a :func:`progress_bar`, or None for nothing) on by the episodes of a batched simulator that
    have ended since the last call, and shows the step they are at: ``tick(sim.done)`` once a step."""

    def __init__(self, bar: Any | None) -> None:
        self.bar, self.ended, self.step = bar, 0, 0

    def __call__(self, done: np.ndarray) -> None:
        self.step += 1
        if self.bar is not None:
            ended = int(done.sum())
            self.bar.set_postfix_str(f"step {self.step}", refresh=False)
            self.bar.update(ended - self.ended)  # redraws at the bar's interval, even when no episode ended
            self.ended = ended


# -------------------------------------------------------------------- run loop
class RunLoop:
    """One run of a learner in its run directory: everything BC, experts and adversarial
    learners share, so that a learner writes only its networks and its per-iteration update.

    Used as::

        with RunLoop(cfg, algo="bc", resume=resume, hints={...}) as loop:  # device resolved; lock released at the end
            ...                              # environment / demonstrations
            gen = loop.seed()                # torch, random, numpy; the generator every sample is drawn from
            ...                              # networks and optimisers
            if not loop.start(env=..., nets={"policy": ..., ...}, optimizers={...}):
                return loop.ckpt_path        # its checkpoint is at the last iteration already
            return loop.run(update, desc=..., key_stats=...)

    ``loop.guard`` is the run's divergence guard (it names the last checkpoint written);
    ``loop.env_steps`` counts the environment steps of a learner that collects them (the
    update adds its own; ``None`` for one that does not), across resumes.
    """

    def __init__(self, config: Any, *, algo: str, resume: bool = False, hints: dict[str, str]) -> None:
        self.config, self.algo, self.resume = config, algo, resume
        self.dir = Path(config.out or config.default_out())
        held = [name for name in RUN_FILES if (self.dir / name).exists()]
        if held and not resume and not config.overwrite:
            raise PomilError(f"{self.dir} holds a run ({', '.join(held)}): --resume goes on with it, --overwrite "
                             "replaces it, or choose another --out")
        self.ckpt_path = self.dir / "checkpoint.pt"
        self.device = resolve_device(config.device)
        self.lock = RunLock(self.dir)
        self.guard = DivergenceGuard(self.ckpt_path, hints)
        self.iteration = 0  # the last iteration done: 0, the checkpoint's once resumed, then each one run
        self.env_steps: int | None = None
        self.generator = torch.Generator()
        self.penalty_generator = torch.Generator()
        self.logger: RunLogger | None = None
        self.env: dict[str, Any] = {}
        self.record: dict[str, Any] = {}
        self.nets: dict[str, Any] = {}
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.carried: dict[str, Any] = {}
        self.hand_over: Callable[[], dict[str, Any] | None] | None = None

    def __enter__(self) -> RunLoop:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.lock.release()

    def seed(self) -> torch.Generator:
        """Seed torch's global RNG (network initialisation); the run's generator (:func:`seed_everything`)."""
        self.generator = seed_everything(self.config.seed)
        return self.generator

    def start(self, *, env: dict[str, Any], nets: dict[str, Any], optimizers: dict[str, torch.optim.Optimizer],
              env_steps: bool = True, record: dict[str, Any] | None = None,
              carried: dict[str, Any] | None = None,
              hand_over: Callable[[], dict[str, Any] | None] | None = None) -> bool:
        """Take the lock, resume (under ``--resume``) and write ``config.json``; False when the checkpoint
        is at the last iteration already (nothing to do: a note says so).

        ``env``: the environment's id, kwargs and observation_mask; ``nets``: every network by name, the
        policy as ``policy`` (None entries skipped); ``env_steps``: whether the learner counts them;
        ``record``: what the run chose from the data before training (``--num-codes auto``'s K and its
        evidence), written into config.json after the config and into the checkpoint as ``record``;
        ``carried``: by name, what else the running process holds and the next iteration reads (objects with
        ``state_dict`` and ``load_state_dict``: the batched environment, whose generators draw the next
        episodes' initial states; a code assignment that a step refreshes now and then), kept in the
        checkpoint as ``carried`` so that a resumed run goes on exactly as the run uninterrupted.

        ``penalty_generator`` starts from torch's global RNG as it is here, after the networks are built
        (or restored): the gradient penalty's interpolation weights draw from it, the numbers they drew from
        the global RNG before the penalty had a generator of its own; checkpoints keep it as ``rng.torch``.

        ``hand_over() -> weights or None``: the policy the checkpoint hands over as ``policy`` (what
        :class:`pomil.TrainedPolicy` loads) in place of the running one (None: the running one), which stays
        in ``nets.policy`` for ``--resume`` (``pomil.algos.selection``)."""
        self.env, self.nets, self.optimizers, self.record = env, nets, optimizers, dict(record or {})
        self.hand_over = hand_over
        self.carried = {k: v for k, v in (carried or {}).items() if v is not None}
        self.lock.acquire(self.resume)
        if not self.resume and self.config.overwrite:
            for path in (self.dir / name for name in RUN_FILES):
                if path.is_dir():
                    shutil.rmtree(path)
                else:
                    path.unlink(missing_ok=True)
        config = to_dict(self.config)
        begun = (resume_run(self.ckpt_path, config, nets, optimizers=optimizers, generator=self.generator,
                            device=self.device, config_class=type(self.config),
                            carried=self.carried) if self.resume else RunStart())
        self.iteration = begun.iteration
        self.penalty_generator.set_state(torch.get_rng_state())
        self.env_steps = begun.env_steps if env_steps else None
        self.guard.saved(begun.iteration)
        if self.resume and begun.iteration == self.config.iterations:
            print(f"pomil: note: {self.ckpt_path} is already at iteration {begun.iteration}: nothing to do",
                  file=sys.stderr)
            return False
        write_json(self.dir / "config.json", {"algo": self.algo, **config, **self.record})
        return True

    def run(self, update: Callable[[int], dict[str, float]], *, desc: str, key_stats: tuple[str, ...] = (),
            first_row: dict[str, float] | None = None, evaluate: Callable[[Any], dict[str, float]] | None = None,
            eval_every: int = 0, log_extras: Callable[[], dict[str, float]] | None = None) -> Path:
        """The iterations after :meth:`start`; returns the checkpoint path.  Each calls ``update(iteration) ->
        stats``, then the divergence guard's check of every parameter; an evaluation every ``eval_every`` iterations
        and at the end; a log row every ``log_every`` iterations, at the first and the last, and with every
        evaluation; a checkpoint every ``checkpoint_every`` iterations and at the end.

        A fresh run logs row 0 first: ``first_row`` (a warm start's figures) and the evaluation
        of the initial policy.  ``evaluate(policy) -> stats``; ``log_extras() -> stats``: figures
        added to each log row after the wall-clock ones."""
        cfg = self.config
        self.logger = logger = RunLogger(self.dir, cfg.iterations, self.iteration, cfg.progress, desc=desc,
                                         key_stats=key_stats, resume=self.resume)
        self.guard.on_stop = logger.close
        if self.iteration == 0 and not self.resume:  # a resumed run at 0 (a warm start alone) has its row 0
            row = dict(first_row or {})
            if evaluate is not None:
                row.update(evaluate(self.nets["policy"]), **{"eval/env_steps": 0.0})
            if row:
                logger.log(0, row)
        t_start = time.perf_counter()
        for it in range(self.iteration + 1, cfg.iterations + 1):
            stats = update(it)
            self.guard.params(it, self.nets)
            self.iteration = it
            evaluated = evaluate is not None and eval_every > 0 and (it % eval_every == 0 or it == cfg.iterations)
            if evaluated:
                stats.update(evaluate(self.nets["policy"]), **{"eval/env_steps": float(self.env_steps or 0)})
            if it % cfg.log_every == 0 or it in (1, cfg.iterations) or evaluated:
                stats.update(self._rates(time.perf_counter() - t_start), **(log_extras() if log_extras else {}))
                logger.log(it, stats)
            if it % cfg.checkpoint_every == 0 or it == cfg.iterations:
                save_run_checkpoint(self.ckpt_path, logger, self.guard, iteration=it, payload=self.state())
            logger.update()
        if cfg.iterations == 0:  # a learner allowed no iterations (the adversarial warm start alone)
            save_run_checkpoint(self.ckpt_path, logger, self.guard, iteration=0, payload=self.state())
        logger.close()
        return self.ckpt_path

    def _rates(self, elapsed: float) -> dict[str, float]:
        rates = {"time/elapsed_s": elapsed}
        if self.env_steps is not None:
            rates["time/env_steps_per_s"] = self.env_steps / max(elapsed, 1e-9)
        return rates

    def state(self) -> dict[str, Any]:
        """The checkpoint (version 1) of every learner, less its iteration: ``algo``, ``config``,
        ``env``, ``policy_arch``, ``policy`` (what :class:`pomil.TrainedPolicy` loads), ``optimizers``
        and ``rng`` (what ``--resume`` restores, with ``carried`` when :meth:`start` was given it);
        ``nets`` (every network by name) when there is more
        than the policy; ``obs_norm`` when the policy normalises its observations (experts);
        ``env_steps`` when the learner counts them; ``record`` when the run chose something from the data
        (:meth:`start`)."""
        policy = self.nets["policy"]
        payload = {"algo": self.algo, "config": to_dict(self.config), "env": self.env,
                   "policy_arch": policy.arch.to_dict(), "policy": policy.state_dict()}
        handed = self.hand_over() if self.hand_over is not None else None
        if handed is not None:
            payload["policy"] = handed
        if set(self.nets) != {"policy"}:
            payload["nets"] = {k: net.state_dict() for k, net in self.nets.items() if net is not None}
        if self.nets.get("obs_norm") is not None:
            payload["obs_norm"] = self.nets["obs_norm"].state_dict()
        payload["optimizers"] = {k: opt.state_dict() for k, opt in self.optimizers.items()}
        payload["rng"] = rng_state(self.generator, self.penalty_generator)
        if self.carried:
            payload["carried"] = {k: obj.state_dict() for k, obj in self.carried.items()}
        if self.env_steps is not None:
            payload["env_steps"] = self.env_steps
        if self.record:
            payload["record"] = self.record
        return payload
