"""The package path, as a user who installs pomil's wheel meets it: the wheel built from this checkout, installed
into a fresh virtual environment outside it, run from an empty folder (shipped experts, default run directories,
the overwrite refusal, evaluation). The new environment takes its dependencies from this one's packages, after
its own: pomil itself comes from the wheel, never from the checkout."""

import json
import math
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(cmd, cwd, code=0):
    r = subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, text=True, timeout=900,
                       env={"PATH": "/usr/bin:/bin", "HOME": str(cwd), "OMP_NUM_THREADS": "1"})
    assert r.returncode == code, r.stdout + r.stderr
    return r


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(the fresh environment's ``pomil`` command, the wheel's file names)."""
    tmp = tmp_path_factory.mktemp("package")
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", tmp / "dist", ROOT],
         tmp)
    (wheel,) = (tmp / "dist").glob("pomil-*.whl")
    env = tmp / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", env], tmp)
    python = env / "bin" / "python"
    purelib = _run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp).stdout.strip()
    purelib = Path(purelib)
    (purelib / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    _run([sys.executable, "-m", "pip", "--python", python, "install", "-q", "--no-deps", "--no-index", wheel], tmp)
    return env / "bin" / "pomil", zipfile.ZipFile(wheel).namelist()


def test_the_wheel_holds_the_shipped_experts_and_experiment_specs(installed):
    _, names = installed
    assert {"pomil/py.typed", "pomil/experiments/circles.toml", "pomil/experts/hopper-forward.pt",
            "pomil/experts/hopper-standard-backward.pt"} <= set(names)
    docs = {f"pomil/docs/{p.name}" for p in (ROOT / "docs").glob("*.md")}
    assert "pomil/docs/hopper.md" in docs and docs <= set(names)  # every page of docs/
    assert not any(n.startswith(("tests/", "data/", "results/")) for n in names)


def test_the_installed_package_runs_from_an_empty_folder(installed, tmp_path):
    pomil, _ = installed
    from pomil import __version__

    assert _run([pomil, "--version"], tmp_path).stdout == f"pomil {__version__}\n"
    where = _run([pomil.parent / "python", "-c", "import pomil; print(pomil.__file__)"], tmp_path).stdout
    assert where.startswith(str(pomil.parents[1])), where  # the wheel's copy, not the checkout's
    r = _run([pomil, "demos", "hopper", "--episodes", "1", "--out", "d.npz"], tmp_path)  # the shipped experts
    assert r.stdout.startswith("wrote d.npz: 2 episodes (1 per task, paper setting)")
    train = [pomil, "train", "bc", "--demos", "d.npz", "--iterations", "2", "--hidden-size", "8", "--no-progress"]
    assert _run(train, tmp_path).stdout == "wrote runs/bc-gru/checkpoint.pt\n"
    refused = _run(train, tmp_path, code=2)
    assert refused.stderr.startswith("pomil: error: runs/bc-gru holds a run (") and refused.stderr.count("\n") == 1
    _run([*train, "--overwrite"], tmp_path)
    topics = _run([pomil, "docs"], tmp_path).stdout.splitlines()
    assert len(topics) == len(list((ROOT / "docs").glob("*.md"))) and topics[1].startswith("hopper     Hopper")
    assert _run([pomil, "docs", "hopper"], tmp_path).stdout == (ROOT / "docs" / "hopper.md").read_text()
    scores = json.loads(_run([pomil, "evaluate", "runs/bc-gru/checkpoint.pt", "--demos", "d.npz",
                              "--episodes-per-code", "2", "--json"], tmp_path).stdout)
    assert set(scores["tasks"]) == {"forward", "backward"} and scores["episodes_per_code"] == 2
    assert all(math.isfinite(t["normalised_return"]) for t in scores["tasks"].values())


def test_the_sdist_carries_the_tests_and_what_they_read(tmp_path):
    """An unpacked sdist runs the suite from its own src/ (``PYTHONPATH=src pytest``): it holds every file of tests/
    (conftest, fixtures) and scripts/, the benchmark scripts and the demonstrations the tests read; the committed
    results stay in the repository."""
    import tarfile

    build = f"from setuptools.build_meta import build_sdist; print(build_sdist({str(tmp_path)!r}))"
    name = _run([sys.executable, "-c", build], ROOT).stdout.strip().splitlines()[-1]
    with tarfile.open(tmp_path / name) as tar:
        held = {m.split("/", 1)[1] for m in tar.getnames() if "/" in m}

    def files(folder):
        return {p.relative_to(ROOT).as_posix() for p in (ROOT / folder).rglob("*")
                if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc"}

    expected = files("tests") | files("scripts") | (files("benchmarks") - files("benchmarks/results"))
    assert {"tests/conftest.py", "data/circles.npz", "data/hopper-paper.npz", "pyproject.toml", "LICENSE", "setup.py",
            "docs/hopper.md"} <= held
    assert any(h.startswith("tests/fixtures/") for h in held)
    assert expected <= held, sorted(expected - held)[:10]
    replayed = {"benchmarks/results/num_codes_seeds.json", "benchmarks/results/num_codes_heldout.json"}
    assert replayed <= held  # the recorded searches tests/algos/test_num_codes.py replays
    assert not any(h.startswith(("results/", "benchmarks/results/", ".git")) for h in held - replayed)
