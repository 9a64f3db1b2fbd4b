"""Builds the native module with the project's own CMake build (the client library and its Draco,
gRPC and protobuf, all from Debian packages) and puts it into the package.

    python3 -m venv --system-site-packages .venv
    .venv/bin/pip install --no-build-isolation ./python

LSQSURF_BUILD_DIR chooses the CMake build folder (default: build/python in the checkout); a build
that compiled the same sources before (the release preset) is reused through ccache.
"""
import os
import pathlib
import shutil
import subprocess
import sys

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

CHECKOUT = pathlib.Path(__file__).resolve().parent.parent


class CMakeBuild(build_ext):
    def build_extension(self, ext):
        build_dir = pathlib.Path(os.environ.get("LSQSURF_BUILD_DIR", CHECKOUT / "build" / "python"))
        env = dict(os.environ, CCACHE_BASEDIR=str(CHECKOUT), CCACHE_NOHASHDIR="true")
        generator = ["-G", "Ninja"] if shutil.which("ninja") else []
        subprocess.run(
            ["cmake", "-S", str(CHECKOUT), "-B", str(build_dir), *generator, "-DCMAKE_BUILD_TYPE=Release",
             "-DLSQSURF_BUILD_TESTS=OFF", "-DLSQSURF_BUILD_BENCH=OFF", "-DLSQSURF_BUILD_PYTHON=ON",
             f"-DPython3_EXECUTABLE={sys.executable}"],
            check=True, env=env)
        subprocess.run(["cmake", "--build", str(build_dir), "--target", "lsqsurf_python"], check=True, env=env)
        built = next((build_dir / "python" / "lsqsurf").glob("_native*.so"))
        target = pathlib.Path(self.get_ext_fullpath(ext.name))
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(built, target)


setup(ext_modules=[Extension("lsqsurf._native", sources=[])], cmdclass={"build_ext": CMakeBuild})
