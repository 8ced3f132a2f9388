"""Build torch_diffavatar and its C++ extension.

Install torch first, then build without isolation so the extension compiles against the
torch that is installed (see README):

    pip install torch==2.13.0
    pip install --no-build-isolation -e .
"""

import glob
import os

from setuptools import find_packages, setup

TORCH_PIN = "torch==2.13.0"


def _extensions():
    sources = sorted(glob.glob(os.path.join("csrc", "*.cpp")))
    if not sources or os.environ.get("DIFFAVATAR_NO_EXTENSION"):
        return [], {}
    from torch.utils.cpp_extension import BuildExtension, CppExtension

    ext = CppExtension(
        name="torch_diffavatar._C",
        sources=sources,
        # no errno from the maths functions (never read): GCC vectorises sqrt only then
        extra_compile_args=["-O3", "-fopenmp", "-std=c++20", "-fno-math-errno"],
        extra_link_args=["-fopenmp"],
        py_limited_api=False,
    )
    return [ext], {"build_ext": BuildExtension.with_options(no_python_abi_suffix=True)}


ext_modules, cmdclass = _extensions()

setup(
    name="torch_diffavatar",
    version="0.1.0",
    description="Simulation-ready avatars from one noisy scan: differentiable XPBD cloth in PyTorch",
    packages=find_packages(include=["torch_diffavatar", "torch_diffavatar.*"]),
    package_data={
        "torch_diffavatar": [
            "pattern/templates/*.json",
            "pattern/templates/LICENSE*",
            "data/*",
            "configs/*.yaml",
        ]
    },
    python_requires=">=3.10",
    install_requires=[
        TORCH_PIN,
        "numpy",
        "scipy",
        "triangle",
        "trimesh",
        "anny==0.6.2",
        "pyyaml",
        "pillow",
        "tqdm",
        "tensorboard",
    ],
    extras_require={
        "test": ["pytest", "ruff", "rtree"],
        "newton": ["warp-lang==1.19.0", "newton==1.8.0"],
        "ray": ["ray>=2.9"],
    },
    ext_modules=ext_modules,
    cmdclass=cmdclass,
    entry_points={"console_scripts": ["diffavatar=torch_diffavatar.cli:main"]},
)
