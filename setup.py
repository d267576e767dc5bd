"""Builds torchmanifold and its C++ extension ``torchmanifold._C`` from ``csrc/``.

Build with ``pip install --no-build-isolation -e .`` so the extension compiles against the torch
already in the environment. ``DEBUG=1`` builds without optimisation.
"""
import glob
import os

from setuptools import find_packages, setup
from torch.utils.cpp_extension import BuildExtension, CppExtension, CUDAExtension, CUDA_HOME
import torch


def get_extensions():
    debug = os.getenv("DEBUG", "0") == "1"
    sources = sorted(glob.glob("csrc/**/*.cpp", recursive=True))
    cuda_sources = sorted(glob.glob("csrc/**/*.cu", recursive=True))
    opt = ["-O0", "-g"] if debug else ["-O3"]
    extra_compile_args = {"cxx": opt + ["-fopenmp", "-std=c++17"]}
    extra_link_args = ["-fopenmp"]
    extension = CppExtension
    use_cuda = bool(cuda_sources) and torch.cuda.is_available() and CUDA_HOME is not None
    if use_cuda or os.getenv("FORCE_CUDA", "0") == "1":
        extension = CUDAExtension
        sources += cuda_sources
        extra_compile_args["nvcc"] = opt + ["--use_fast_math"]
    return [
        extension(
            "torchmanifold._C",
            sources,
            include_dirs=[os.path.abspath("csrc")],
            extra_compile_args=extra_compile_args,
            extra_link_args=extra_link_args,
        )
    ]


setup(
    packages=find_packages(include=["torchmanifold", "torchmanifold.*"]),
    package_data={"torchmanifold": ["render/shaders/*", "render/scenes/*"]},
    ext_modules=get_extensions(),
    cmdclass={"build_ext": BuildExtension.with_options(use_ninja=True)},
)
