"""The shared run machinery under failure: divergence, full or read-only output, two
writers, resume bookkeeping (environment steps, iterations below the checkpoint)."""

import csv
import errno
import json
import math
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

import pomil.algos.adversarial as adversarial
import pomil.algos.bc as bc
import pomil.algos.expert as expert
import pomil.algos.warm_start as warm_start
import pomil.data
from pomil.algos.adversarial import AdversarialConfig, train_adversarial
from pomil.algos.bc import BCConfig, train_bc
from pomil.algos.expert import ExpertConfig, train_expert
from pomil.api import TrainedPolicy
from pomil.cli import main
from pomil.errors import DivergenceError, PomilError, RunBusyError
from pomil.training import RunLock, load_checkpoint, save_checkpoint

SRC = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "src")


def _bc(demos_path, out, **kw):
    return BCConfig(**{**dict(demos=str(demos_path), out=str(out), progress=False, log_every=1, iterations=10,
                              hidden_size=16, policy="mlp", checkpoint_every=5, batch_episodes=16), **kw})


def _adv(demos_path, out, **kw):
    return AdversarialConfig(**{**dict(demos=str(demos_path), out=str(out), iterations=4, num_envs=8, hidden_size=16,
                                       critic_steps=1, critic_batch=8, ppo_epochs=1, minibatches=2, eval_every=2,
                                       eval_episodes=4, progress=False, log_every=1, warm_start_iterations=0,
                                       checkpoint_every=2), **kw})


def _nan_on_call(monkeypatch, module, name, call, key):
    """Replace module.name by a wrapper whose ``call``-th result has stats[key] = NaN (the loss)."""
    real = getattr(module, name)
    calls = []

    def wrapper(*args, **kwargs):
        out = real(*args, **kwargs)
        calls.append(1)
        if len(calls) == call:
            stats = out[1] if isinstance(out, tuple) else out
            stats[key] = math.nan
        return out

    monkeypatch.setattr(module, name, wrapper)


# ------------------------------------------------------------------ divergence
def test_bc_nan_at_a_chosen_iteration_stops_there_keeps_the_checkpoint_and_resumes_with_a_lower_lr(
        demos_path, tmp_path, monkeypatch):
    out = tmp_path / "bc"
    _nan_on_call(monkeypatch, bc, "bc_step", 7, "bc/nll")
    with pytest.raises(DivergenceError) as err:
        train_bc(_bc(demos_path, out))
    assert str(err.value) == (
        "iteration 7: bc loss (negative log-likelihood) is nan (the run diverged); try a lower --lr (now 0.001); "
        f"{out / 'checkpoint.pt'} (iteration 5) is unchanged: continue it with --resume and a lower --lr")
    assert load_checkpoint(out)["iteration"] == 5
    assert not (out / "run.lock").exists()  # released
    monkeypatch.undo()
    train_bc(_bc(demos_path, out, lr=1e-4), resume=True)
    ckpt = load_checkpoint(out)
    assert ckpt["iteration"] == 10 and ckpt["config"]["lr"] == 1e-4
    assert ckpt["optimizers"]["policy"]["param_groups"][0]["lr"] == 1e-4  # the new rate, not the checkpoint's


def test_bc_with_a_huge_learning_rate_exits_3_in_one_line(demos_path, tmp_path, capsys):
    code = main(["train", "bc", "--demos", str(demos_path), "--out", str(tmp_path / "r"), "--lr", "1e3",
                 "--policy", "mlp",
                 "--hidden-size", "16", "--iterations", "50", "--checkpoint-every", "1", "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 3 and len(err) == 1 and err[0].startswith("pomil: error: iteration "), err
    assert "(the run diverged); try a lower --lr (now 1000); " in err[0]
    ckpt = load_checkpoint(tmp_path / "r")  # the last checkpoint written is finite, and loads
    assert 1 <= ckpt["iteration"] < 50


def test_adversarial_nan_critic_loss_at_iteration_3_keeps_checkpoint_2_and_resumes(demos_path, tmp_path, monkeypatch):
    out = tmp_path / "adv"
    _nan_on_call(monkeypatch, adversarial, "critic_loss", 3, "critic/loss")
    with pytest.raises(DivergenceError, match=r"^iteration 3: critic loss is nan \(the run diverged\); try a lower "
                                              r"--lr-critic \(now 0.0005\); .*\(iteration 2\) is unchanged"):
        train_adversarial(_adv(demos_path, out))
    before = (out / "checkpoint.pt").read_bytes()
    assert load_checkpoint(out)["iteration"] == 2
    with open(out / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["iteration"] for r in rows] == ["0", "1", "2"]  # flushed up to the iteration that diverged
    monkeypatch.undo()
    with pytest.raises(PomilError,
                       match=r"changed: hidden_size\)"):  # learning rates may change on resume, nothing else
        train_adversarial(_adv(demos_path, out, lr_value=1e-4, hidden_size=32), resume=True)
    assert (out / "checkpoint.pt").read_bytes() == before
    train_adversarial(_adv(demos_path, out, lr_critic=1e-4), resume=True)
    ckpt = load_checkpoint(out)
    assert ckpt["iteration"] == 4 and ckpt["optimizers"]["critic"]["param_groups"][0]["lr"] == 1e-4


def test_the_issues_divergent_learning_rates_end_in_one_line_with_exit_3(demos_path, tmp_path, capsys):
    code = main(["train", "infogail-pomdp", "--demos", str(demos_path), "--out", str(tmp_path / "r"), "--lr", "1e4",
                 "--lr-critic", "1e4", "--lr-value", "1e4", "--iterations", "6", "--num-envs", "8",
                 "--hidden-size", "16",
                 "--critic-steps", "1", "--warm-start-iterations", "0", "--eval-every", "0", "--checkpoint-every", "1",
                 "--no-progress"])
    err = [line for line in capsys.readouterr().err.strip().splitlines() if not line.startswith("pomil: note:")]
    assert code == 3 and len(err) == 1 and "(the run diverged)" in err[0], err
    if (tmp_path / "r" / "checkpoint.pt").exists():
        load_checkpoint(tmp_path / "r")  # finite


def test_warm_start_is_guarded(demos_path, tmp_path, monkeypatch):
    _nan_on_call(monkeypatch, warm_start, "bc_step", 3, "bc/nll")
    with pytest.raises(DivergenceError) as err:
        train_adversarial(_adv(demos_path, tmp_path / "w", warm_start_iterations=5))
    assert str(err.value) == ("warm-start step 3: warm-start loss (negative log-likelihood) is nan (the run diverged); "
                              "try a lower --warm-start-lr (now 0.01); no checkpoint of this run was written: "
                              "start it again with a lower --warm-start-lr")
    assert not (tmp_path / "w" / "checkpoint.pt").exists()


def test_nan_gradient_and_reward_are_named(demos_path, tmp_path, monkeypatch):
    real = adversarial.rewards

    def nan_reward(*args, **kwargs):
        r, s = real(*args, **kwargs)
        return r.index_fill(1, torch.tensor([3]), math.inf), s

    monkeypatch.setattr(adversarial, "rewards", nan_reward)
    with pytest.raises(DivergenceError,
                       match=r"^iteration 1: reward is inf .*try a lower --lr-critic \(now 0.0005\) or "
                                              r"--lr-posterior \(now 0.0002\); "):
        train_adversarial(_adv(demos_path, tmp_path / "r"))
    monkeypatch.undo()
    real_loss = adversarial.posterior_loss

    def nan_grad(*args, **kwargs):  # the reported loss stays finite; its gradient is 0 * inf = NaN
        loss, s = real_loss(*args, **kwargs)
        return loss + 0 * (loss * math.inf), s

    monkeypatch.setattr(adversarial, "posterior_loss", nan_grad)
    with pytest.raises(DivergenceError, match=r"^iteration 1: posterior gradient is nan .*--lr-posterior"):
        train_adversarial(_adv(demos_path, tmp_path / "g"))


def test_expert_ppo_loop_is_guarded(tmp_path, monkeypatch):
    _nan_on_call(monkeypatch, expert, "ppo_loss", 3, "ppo/value_loss")
    cfg = ExpertConfig(env_id="Pendulum-v1", task="none", setting="standard", env_kwargs=("max_episode_steps=20",),
                       out=str(tmp_path / "e"), iterations=3, num_envs=2, ppo_epochs=1, minibatches=1, hidden_size=8,
                       progress=False, checkpoint_every=1)
    with pytest.raises(DivergenceError, match=r"^iteration 3: value loss is nan .*--lr \(now 0.0003\); "
                                              r".*\(iteration 2\) is unchanged"):
        train_expert(cfg)
    monkeypatch.undo()
    train_expert(cfg, resume=True)
    ckpt = load_checkpoint(tmp_path / "e")
    assert ckpt["iteration"] == 3 and ckpt["env_steps"] == 3 * 2 * 20  # counted across the resume


# ------------------------------------------------------- non-finite checkpoints
def _poisoned_checkpoint(demos_path, tmp_path):
    ckpt = train_bc(_bc(demos_path, tmp_path / "ok", iterations=2))
    payload = torch.load(ckpt, weights_only=True)
    payload["policy"]["log_std"] = torch.full_like(payload["policy"]["log_std"], math.nan)
    bad = tmp_path / "nan.pt"
    torch.save(payload, bad)  # as an older pomil could have written it
    return payload, bad


def test_non_finite_checkpoints_are_never_written_and_loaders_refuse_them(demos_path, tmp_path, capsys):
    payload, bad = _poisoned_checkpoint(demos_path, tmp_path)
    target = tmp_path / "ok" / "checkpoint.pt"
    before = target.read_bytes()
    with pytest.raises(DivergenceError, match="'policy.log_std' holds NaN/inf"):
        save_checkpoint(target, {k: v for k, v in payload.items() if k not in ("format", "version")})
    assert target.read_bytes() == before
    with pytest.raises(PomilError, match=r"nan.pt: 'policy.log_std' holds NaN/inf \(the run that wrote it diverged\)"):
        TrainedPolicy.load(bad)
    for argv in (["evaluate", str(bad)], ["plot", str(bad), "--out", str(tmp_path / "f.png")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "'policy.log_std' holds NaN/inf" in err, err
    assert not (tmp_path / "f.png").exists()


# --------------------------------------------------------- full / read-only disk
def test_full_disk_at_a_checkpoint_is_one_error_and_the_previous_checkpoint_stays(demos_path, tmp_path, monkeypatch):
    out = tmp_path / "full"
    real_save, real_fdopen = pomil.training.save_checkpoint, os.fdopen
    saves = []

    class FullFile:
        def __init__(self, f):
            self.f = f

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

        def __getattr__(self, name):
            return getattr(self.f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    def save(path, payload):
        saves.append(payload["iteration"])
        if len(saves) == 2:
            monkeypatch.setattr(pomil.data.os, "fdopen", lambda *a, **k: FullFile(real_fdopen(*a, **k)))
        real_save(path, payload)

    monkeypatch.setattr(pomil.training, "save_checkpoint", save)  # what every run's checkpoint goes through
    with pytest.raises(PomilError) as err:
        train_bc(_bc(demos_path, out))
    assert str(err.value) == (f"{out / 'checkpoint.pt'}: cannot write (No space left on device); "
                              "the previous checkpoint.pt is unchanged")
    assert load_checkpoint(out)["iteration"] == 5
    assert sorted(p.name for p in out.iterdir() if p.name.endswith(".tmp")) == []  # nothing half-written
    monkeypatch.undo()
    train_bc(_bc(demos_path, out), resume=True)
    assert load_checkpoint(out)["iteration"] == 10


def test_read_only_run_directory_is_one_error(demos_path, tmp_path, monkeypatch, capsys):
    train_bc(_bc(demos_path, tmp_path / "ro", iterations=5))
    before = (tmp_path / "ro" / "checkpoint.pt").read_bytes()

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(pomil.data.tempfile, "mkstemp", read_only)
    code = main(["train", "bc", "--demos", str(demos_path), "--out", str(tmp_path / "ro"), "--iterations", "10",
                 "--policy", "mlp", "--hidden-size", "16", "--checkpoint-every", "5", "--batch-episodes", "16",
                 "--log-every", "1", "--no-progress", "--resume"])
    assert code == 2
    assert capsys.readouterr().err == (f"pomil: error: {tmp_path / 'ro' / 'config.json'}: cannot write (Read-only file "
                                       "system); the previous config.json is unchanged\n")
    assert (tmp_path / "ro" / "checkpoint.pt").read_bytes() == before
    monkeypatch.setattr("pomil.training.os.open", read_only)
    with pytest.raises(PomilError, match=r"ro2: cannot write to the run directory \(Read-only file system\)"):
        train_bc(_bc(demos_path, tmp_path / "ro2"))


# ---------------------------------------------------------------------- locks
def test_a_second_run_into_a_busy_directory_is_refused_in_one_line(demos_path, tmp_path, capsys):
    out = tmp_path / "busy"
    with RunLock(out) as lock:
        lock.acquire()
        code = main(["train", "bc", "--demos", str(demos_path), "--out", str(out), "--iterations", "2",
                     "--no-progress"])
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1, err
        assert err.startswith(f"pomil: error: {out}: in use by another run (pid {os.getpid()} on ")
        assert err.endswith(f"; lock {out / 'run.lock'}): wait for it to end, or choose another --out\n")
        assert sorted(p.name for p in out.iterdir()) == ["run.lock"]  # no config.json, tb/ or metrics.csv
    assert not (out / "run.lock").exists()


def test_two_real_runs_into_one_directory(demos_path, tmp_path):
    """While a run writes, a second one into its directory is refused and writes nothing there, even with
    --overwrite (which replaces a run only once it holds the directory's lock)."""
    out = tmp_path / "two"
    args = [sys.executable, "-m", "pomil.cli", "train", "bc", "--demos", str(demos_path), "--out", str(out),
            "--policy", "mlp", "--hidden-size", "8", "--batch-episodes", "8", "--no-progress"]
    env = {**os.environ, "PYTHONPATH": SRC}
    first = subprocess.Popen([*args, "--iterations", "10000000", "--seed", "1"], env=env, stderr=subprocess.PIPE,
                             text=True)
    try:
        while not (out / "config.json").exists() and first.poll() is None:  # until the first run has started
            time.sleep(0.05)
        assert first.poll() is None, first.stderr.read()
        second = subprocess.run([*args, "--iterations", "2", "--seed", "2", "--overwrite"], env=env,
                                capture_output=True, text=True, timeout=900)
        assert first.poll() is None  # still writing
    finally:
        first.kill()
        first.wait()
    assert second.returncode == 2 and second.stderr.startswith(f"pomil: error: {out}: in use by another run (pid "
                                                               f"{first.pid} on "), second.stderr
    assert json.loads((out / "config.json").read_text())["seed"] == 1
    assert len(list((out / "tb").iterdir())) == 1  # one run's event file
    if (out / "checkpoint.pt").exists():
        assert load_checkpoint(out)["config"]["seed"] == 1


def test_a_run_into_a_directory_holding_one_is_refused_unless_overwrite_or_resume(demos_path, tmp_path, capsys):
    """A second run into a finished run's directory is one line, exit 2, and changes nothing there; --overwrite
    replaces the run (its tb/ events too); --resume goes on with it."""
    out = tmp_path / "held"
    train_bc(_bc(demos_path, out, iterations=5))
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    events = sorted(p.name for p in (out / "tb").iterdir())
    code = main(["train", "bc", "--demos", str(demos_path), "--out", str(out), "--iterations", "2", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and err == (f"pomil: error: {out} holds a run (checkpoint.pt, metrics.csv, config.json, tb): "
                                 "--resume goes on with it, --overwrite replaces it, or choose another --out\n")
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before
    train_bc(_bc(demos_path, out, iterations=3, seed=4, overwrite=True))
    assert load_checkpoint(out)["iteration"] == 3 and json.loads((out / "config.json").read_text())["seed"] == 4
    assert max(int(r["iteration"]) for r in csv.DictReader((out / "metrics.csv").read_text().splitlines())) == 3
    assert len(list((out / "tb").iterdir())) == 1 and sorted(p.name for p in (out / "tb").iterdir()) != events
    train_bc(_bc(demos_path, out, iterations=5, seed=4), resume=True)
    assert load_checkpoint(out)["iteration"] == 5


def test_each_learner_has_its_own_default_run_directory():
    assert BCConfig().default_out() == "runs/bc-gru" and BCConfig(policy="mlp").default_out() == "runs/bc-mlp"
    assert [AdversarialConfig(learner=n).default_out() for n in ("gail", "infogail", "infogail-pomdp")] == [
        "runs/gail", "runs/infogail", "runs/infogail-pomdp"]
    assert ExpertConfig(task="backward", setting="standard").default_out() == "runs/expert-hopper-backward-standard"
    cheetah = ExpertConfig(env_id="HalfCheetah-v5", task="forward")
    assert cheetah.default_out() == "runs/expert-halfcheetah-forward-paper"


def test_a_lock_left_by_a_killed_run_is_taken_over_by_resume(demos_path, tmp_path):
    out = tmp_path / "stale"
    train_bc(_bc(demos_path, out, iterations=5))
    holder = subprocess.Popen([sys.executable, "-c", "import sys; from pomil.training import RunLock; "
                               "RunLock(sys.argv[1]).acquire(); print('locked', flush=True); sys.stdin.read()",
                               str(out)],  # holds the lock until it is killed (its stdin never closes before)
                              env={**os.environ, "PYTHONPATH": SRC}, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              text=True)
    assert holder.stdout.readline().strip() == "locked"
    with pytest.raises(RunBusyError, match=f"pid {holder.pid} on"):
        train_bc(_bc(demos_path, out), resume=True)
    os.kill(holder.pid, signal.SIGKILL)
    holder.wait()
    assert json.loads((out / "run.lock").read_text())["pid"] == holder.pid  # left behind
    r = subprocess.run([sys.executable, "-m", "pomil.cli", "train", "bc", "--demos", str(demos_path), "--out", str(out),
                        "--iterations", "10", "--policy", "mlp", "--hidden-size", "16", "--checkpoint-every", "5",
                        "--batch-episodes", "16", "--log-every", "1", "--no-progress", "--resume"],
                       env={**os.environ, "PYTHONPATH": SRC}, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr
    assert (f"run.lock was left by pid {holder.pid} on" in r.stderr
            and "which is no longer running; taking it over and continuing from its last checkpoint" in r.stderr)
    assert load_checkpoint(out)["iteration"] == 10 and not (out / "run.lock").exists()


# ------------------------------------------------------------ resume bookkeeping
def test_env_steps_count_the_whole_run_across_resumes(demos_path, tmp_path):
    train_adversarial(_adv(demos_path, tmp_path / "whole"))
    train_adversarial(_adv(demos_path, tmp_path / "split", iterations=2))
    train_adversarial(_adv(demos_path, tmp_path / "split"), resume=True)

    def steps(run):
        return [(r["iteration"], r["eval/env_steps"]) for r in csv.DictReader(open(tmp_path / run / "metrics.csv"))
                if r.get("eval/env_steps")]

    assert steps("whole") == steps("split") == [("0", "0.0"), ("2", str(2 * 8 * 33.0)), ("4", str(4 * 8 * 33.0))]
    assert load_checkpoint(tmp_path / "split")["env_steps"] == 4 * 8 * 33


def test_resume_with_iterations_below_the_checkpoint_is_refused_and_equal_is_nothing_to_do(demos_path, tmp_path,
                                                                                           capsys):
    out = tmp_path / "r"
    train_bc(_bc(demos_path, out))
    before = (out / "checkpoint.pt").read_bytes()
    flags = ["train", "bc", "--demos", str(demos_path), "--out", str(out), "--policy", "mlp", "--hidden-size", "16",
             "--checkpoint-every", "5", "--batch-episodes", "16", "--log-every", "1", "--no-progress", "--resume"]
    assert main([*flags, "--iterations", "4"]) == 2
    assert capsys.readouterr().err == (f"pomil: error: {out / 'checkpoint.pt'}: the checkpoint is at iteration 10, "
                                       "past "
                                       "--iterations 4; nothing to resume (pass --iterations above 10 to continue; the "
                                       "checkpoint is unchanged)\n")
    assert main([*flags, "--iterations", "10"]) == 0
    assert "is already at iteration 10: nothing to do" in capsys.readouterr().err
    assert (out / "checkpoint.pt").read_bytes() == before


def test_the_guard_finds_the_first_nonfinite_tensor_and_lets_large_finite_ones_pass(tmp_path):
    """The fused check over all tensors at once, then the exact one: a NaN anywhere is named, a tensor whose
    norm overflows but whose values are finite passes."""
    from pomil.training import DivergenceGuard, all_finite

    big, nan = torch.full((10_000,), 1e30), torch.tensor([1.0, float("nan")])
    assert not all_finite([big]) and not all_finite([nan]) and all_finite([torch.ones(2), torch.zeros(2).long()])
    guard = DivergenceGuard(tmp_path / "checkpoint.pt", {})
    nets = {"a": torch.nn.Linear(2, 2), "b": None}
    with torch.no_grad():
        nets["a"].weight.fill_(1e30)
    guard.params(3, nets)
    weight = nets["a"].weight
    weight.grad = big[:4].view(2, 2).clone()
    guard.grads(3, "policy", [weight])
    with torch.no_grad():
        nets["a"].bias[1] = float("inf")
    with pytest.raises(DivergenceError, match="iteration 3: a parameter 'bias' is inf"):
        guard.params(3, nets)
    weight.grad[0, 1] = float("nan")
    with pytest.raises(DivergenceError, match="iteration 4: policy gradient is nan"):
        guard.grads(4, "policy", [weight])
