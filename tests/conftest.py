"""Shared fixtures. The Anny model is loaded once per session (its cache is costly; see notes/anny.md)."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(scope="session", autouse=True)
def _single_thread():
    # Measured on the 2-core CI machine: one intra-op thread is faster and steadier for our small ops.
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="session")
def anny_model():
    """The project's one Anny configuration, float64 (tests cast as needed)."""
    from torch_diffavatar.body.anny_model import load_anny

    return load_anny(dtype=torch.float64)


@pytest.fixture(scope="session")
def default_body(anny_model):
    """(verts (Vb, 3) [m] world frame, faces (Fb, 3)) of the default draping body, float64."""
    from torch_diffavatar.body.anny_model import default_body_mesh

    return default_body_mesh(anny_model=anny_model)


@pytest.fixture(scope="session")
def skirt_scan(anny_model):
    """A small synthetic skirt scan (`make_draped_scan` at 5 cm, 8k points) with its ground truth."""
    from torch_diffavatar.synthetic_scans import make_draped_scan

    torch.manual_seed(0)
    phenotypes = dict(gender=0.5, age=0.5, muscle=0.5, weight=0.45, height=0.55, proportions=0.5)
    return make_draped_scan(
        "skirt",
        anny_model=anny_model,
        seed=3,
        phenotypes=phenotypes,
        spacing=0.05,
        garment_points=4000,
        body_points=4000,
        noise=0.002,
        hole_fraction=0.1,
    )


@pytest.fixture(scope="module")
def skirt_problem():
    """`helpers_fit.skirt_problem`: a coarse float64 skirt, sewn, and the drape of a longer one as target."""
    from helpers_fit import skirt_problem

    return skirt_problem()


@pytest.fixture
def read_only_folder(tmp_path):
    """A folder that cannot be written into (skipped as root, who writes anyway); writable again after."""
    import os

    if os.geteuid() == 0:
        pytest.skip("root writes into read-only folders")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    yield locked
    locked.chmod(0o700)
