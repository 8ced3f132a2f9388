"""A wheel carries what an installed fit needs: built, installed into a fresh virtual environment, it
finds each garment's own config inside the package (not a `configs/` beside a source checkout)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

CHECK = """
import sys
from pathlib import Path
import torch_diffavatar
from torch_diffavatar.fit import default_config_path, load_config
venv = Path(sys.prefix).resolve()
assert venv in Path(torch_diffavatar.__file__).resolve().parents, torch_diffavatar.__file__
path = default_config_path("pants")
assert path is not None and venv in path.resolve().parents, path
config = load_config(garment="shorts")  # a template without its own config takes its kind's
assert config.iterations == 60 and config.template == "shorts", config
print("ok", path)
"""


@pytest.mark.slow
def test_a_wheel_installed_in_a_fresh_venv_reads_the_garment_configs(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    for name in ("setup.py", "pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    shutil.copytree(
        ROOT / "torch_diffavatar",
        src / "torch_diffavatar",
        ignore=shutil.ignore_patterns("*.so", "__pycache__"),
    )
    env = dict(os.environ, DIFFAVATAR_NO_EXTENSION="1", PIP_DISABLE_PIP_VERSION_CHECK="1")
    env.pop("PYTHONPATH", None)
    wheels = tmp_path / "wheels"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-build-isolation",
            "--no-deps",
            "-q",
            "-w",
            str(wheels),
            str(src),
        ],
        check=True,
        env=env,
        cwd=tmp_path,
    )
    (wheel,) = wheels.glob("torch_diffavatar-*.whl")
    venv = tmp_path / "venv"
    # the venv sees this machine's packages (torch, anny, ...); its own torch_diffavatar comes first
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True)
    python = venv / "bin" / "python"
    subprocess.run([python, "-m", "pip", "install", "--no-deps", "-q", str(wheel)], check=True, env=env)
    out = subprocess.run(
        [python, "-c", CHECK], check=True, env=env, cwd=tmp_path, capture_output=True, text=True
    )
    assert out.stdout.startswith("ok")
