"""The wheel installs and works outside the repository.

Builds the wheel from a copy of the sources, installs it into a fresh virtual environment
whose dependencies (torch, Warp, SB3, gymnasium) come from the *running* environment, so
nothing is downloaded (``--no-deps --no-index``: offline; the venv has no pip of its own,
this interpreter's ``pip --python`` installs into it), and from a folder outside the
repository runs ``counterplay --version``, a tiny ``counterplay run`` (the shipped anchor
and recipe, read from inside the installed package) and ``counterplay outcomes`` with the
README's ``zoo/anchor.zip`` spelling.

``venv --system-site-packages`` alone is not enough: run from inside a virtual environment,
``python -m venv`` bases the new venv on the *base* interpreter, whose site-packages may lack
the dependencies the running venv has. So the new venv also gets a ``.pth`` file that adds the
running environment's site-packages (:func:`running_site_packages`) after its own.
"""

from __future__ import annotations

import json
import os
import shutil
import site
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def running_site_packages() -> list[str]:
    """The site-packages folders of the running environment (a venv's own included)."""
    paths = [sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"], *site.getsitepackages()]
    return [p for i, p in enumerate(paths) if p not in paths[:i] and os.path.isdir(p)]


def _run(argv: list[str], cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env["PYTHONNOUSERSITE"] = "1"
    done = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"{argv} failed ({done.returncode}):\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """A fresh venv with the wheel installed; returns its bin folder."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, src / name)
    for package in ("cpsim", "cpalgo"):  # a copy: the build writes build/ and *.egg-info
        shutil.copytree(ROOT / package, src / package, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    dist = tmp / "dist"
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q",
          "-w", str(dist), str(src)], cwd=tmp)
    wheels = list(dist.glob("counterplay-*.whl"))
    assert len(wheels) == 1, wheels
    venv = tmp / "venv"
    # no pip inside the venv (no ensurepip needed): this interpreter's pip installs into it
    _run([sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", str(venv)], cwd=tmp)
    bindir = venv / ("Scripts" if os.name == "nt" else "bin")
    # the running environment's packages, also when this interpreter is itself a venv's
    venv_site = _run([str(bindir / "python"), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                     cwd=tmp).stdout.strip()
    lines = [f"import site; site.addsitedir({d!r})" for d in running_site_packages()]
    (Path(venv_site) / "_running_env.pth").write_text("\n".join(lines) + "\n")
    _run([sys.executable, "-m", "pip", "--python", str(bindir / "python"), "install", "--no-deps", "--no-index",
          "--ignore-installed", "-q", str(wheels[0])], cwd=tmp)
    return bindir


def test_installed_wheel_runs_outside_the_repository(installed, tmp_path):
    work = tmp_path / "elsewhere"
    work.mkdir()
    where = _run([str(installed / "python"), "-c",
                  "import cpalgo, cpsim; from cpalgo.recipes import shipped_path; "
                  "print(cpalgo.__file__); print(cpsim.__file__); print(shipped_path('anchor.zip'))"], cwd=work)
    for line in where.stdout.split():
        path = Path(line).resolve()
        assert ROOT not in path.parents and str(installed.parent) in str(path), line  # the venv's copy

    # the new venv sees the running environment's packages (run from a venv, not only the base's)
    seen = _run([str(installed / "python"), "-c", "import sys; print('\\n'.join(sys.path))"], cwd=work).stdout
    seen_paths = {os.path.realpath(p) for p in seen.splitlines() if p}
    for folder in running_site_packages():
        assert os.path.realpath(folder) in seen_paths, (folder, seen)

    version = _run([str(installed / "counterplay"), "--version"], cwd=work)
    assert version.stdout.strip().startswith("counterplay ")

    out = work / "runs" / "tiny"
    _run([str(installed / "counterplay"), "run", "--worlds", "1", "--scenarios", "2", "--timesteps", "1",
          "--eval-tasks", "1", "--threads", "1", "--no-progress", "--out", str(out)], cwd=work)
    summary = (out / "summary.json").read_text()
    assert json.loads(summary) and (out / "summary.md").is_file()
    assert list(out.rglob("*.zip")), "no checkpoint written"
    assert str(ROOT) not in summary  # the shipped anchor and recipe came from the installed package

    rates = work / "anchor.json"
    _run([str(installed / "counterplay"), "outcomes", "--model", "zoo/anchor.zip", "--tasks", "1",
          "--threads", "1", "--out", str(rates)], cwd=work)
    assert json.loads(rates.read_text())["outcomes"]["agents"] > 0
