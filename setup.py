"""The compiled kernels (o3dreg/_kernels.c): a plain C library that o3dreg loads with ctypes.

Everything else about the package is in pyproject.toml.
"""

import os

from setuptools import Extension, setup

# No floating-point contraction (a * b + c fused where the machine allows): the same results on
# every machine, and the same sums as NumPy's.
FLAGS = ["/O2", "/fp:precise"] if os.name == "nt" else ["-O3", "-ffp-contract=off", "-std=c99"]

setup(ext_modules=[Extension("o3dreg._kernels", ["o3dreg/_kernels.c"], extra_compile_args=FLAGS)])
