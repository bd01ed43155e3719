#!/usr/bin/env bash
# Prepares, on a CPU machine, what a bare GPU machine needs for scripts/gpu_check.sh (issue 35;
# `make gpu-prepare`). The lent GPU machines (docs/gpu.md) have Python 3.12 with torch
# 2.11.0+cu130 and no network; this puts beside the working tree, in folders .gitignore keeps
# out of commits and the device tool's `carry` takes along:
#
#   .whl/   the wheels of the packages such a machine lacks (cp312, manylinux x86-64)
#   .gpu/   gsplat's CUDA extension built ahead for sm_90 (H100, H200) as the module
#           gsplat.csrc, which gsplat imports before it falls back to a JIT compile; and a copy
#           of ../shared/data/scenes for the tests that compare gsplat on the shared scenes
#
# The extension is compiled against PyPI's torch 2.11.0 (the cu130 build, the GPU machines'
# own: the same git revision), with this machine's nvcc 13.0 and the CUDA 13 headers of the
# nvidia wheels torch depends on, under Python 3.12 (pyenv's, or PY312=...). Built once it
# takes about 4 minutes on 2 cores; gsplat's own JIT compile of the same sources on the GPU
# machine would cost device time. Idempotent: what is there is kept.
set -euo pipefail
REPO=$(cd "$(dirname "$0")/.." && pwd)
cd "$REPO"
if [ -z "${PY312:-}" ]; then
  PY312=python3.12
  "$PY312" -c pass 2> /dev/null || PY312=$(ls -d "$HOME"/.pyenv/versions/3.12*/bin/python 2> /dev/null | tail -1)
fi
BUILD=${GPU_BUILD_DIR:-/tmp/nhfd-gpu-build}
TORCH_VERSION=2.11.0
GSPLAT_VERSION=1.5.3
ARCH=${GPU_ARCH:-9.0}
# The packages the GPU machines lack, at the versions this project's .venv resolves to.
WHEELS="gsplat==$GSPLAT_VERSION pydantic==2.14.4 pydantic_core==2.50.5 annotated-types
  typing-inspection==0.4.5 typing_extensions plyfile==1.1.5 zstandard==0.25.0 kornia==0.9.0
  kornia_rs==0.2.0 pyserial==3.5 hidapi==0.15.0 pyusb==1.3.1 libusb-package==1.0.30.0
  importlib_resources"
PLATFORMS="--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64"

mkdir -p .whl .gpu "$BUILD"
echo "== wheels into .whl/"
for spec in $WHEELS; do
  # shellcheck disable=SC2086
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp $PLATFORMS -d .whl "$spec"
done

echo "== shared scenes into .gpu/shared/data/scenes"
if [ -d ../shared/data/scenes ]; then
  mkdir -p .gpu/shared/data && cp -r ../shared/data/scenes .gpu/shared/data/
else
  echo "no ../shared/data/scenes: the shared-scene gsplat tests will skip on the GPU machine"
fi

SUFFIX=$("$PY312" -c "import sysconfig; print(sysconfig.get_config_var('EXT_SUFFIX'))")
OUT_SO=.gpu/gsplat_csrc$SUFFIX
if [ -f "$OUT_SO" ]; then
  echo "== $OUT_SO is there (delete it to build again)"
  exit 0
fi
echo "== gsplat $GSPLAT_VERSION's CUDA extension for sm_${ARCH/./} against torch $TORCH_VERSION"
command -v nvcc > /dev/null || { echo "no nvcc: install CUDA 13.0's compiler first"; exit 1; }
if [ ! -x "$BUILD/venv/bin/python" ]; then
  "$PY312" -m venv "$BUILD/venv"
  # torch's own dependencies bring the CUDA 13 headers (cuBLAS, cuSPARSE, cuSOLVER) that
  # ATen's CUDA headers include.
  "$BUILD/venv/bin/pip" install -q "torch==$TORCH_VERSION" ninja setuptools wheel
fi
rm -rf "$BUILD/src" && mkdir -p "$BUILD/src"
(cd "$BUILD/src" && unzip -q "$REPO"/.whl/gsplat-"$GSPLAT_VERSION"-py3-none-any.whl 'gsplat/*')
cat > "$BUILD/src/setup_csrc.py" <<'EOF'
# gsplat.csrc with gsplat/cuda/_backend.py's JIT flags and sources.
import glob, os
from setuptools import setup
from torch.utils.cpp_extension import BuildExtension, CUDAExtension
import nvidia
P = "gsplat/cuda"
cuda13 = os.path.join(nvidia.__path__[0], "cu13", "include")
sources = sorted(glob.glob(f"{P}/csrc/*.cu")) + sorted(glob.glob(f"{P}/csrc/*.cpp")) + [f"{P}/ext.cpp"]
setup(name="gsplat_csrc", cmdclass={"build_ext": BuildExtension}, ext_modules=[CUDAExtension(
    "gsplat.csrc", sources,
    include_dirs=[os.path.abspath(f"{P}/include"), os.path.abspath(f"{P}/csrc/third_party/glm"), cuda13],
    extra_compile_args={"cxx": ["-O3", "-Wno-attributes"], "nvcc": ["-O3", "-use_fast_math"]})])
EOF
(cd "$BUILD/src" && CUDA_HOME=${CUDA_HOME:-/usr/local/cuda} TORCH_CUDA_ARCH_LIST=$ARCH \
  MAX_JOBS=$(nproc) "$BUILD/venv/bin/python" setup_csrc.py build_ext --inplace > build.log 2>&1) ||
  { tail -30 "$BUILD/src/build.log"; exit 1; }
# Without its debug sections the extension is 14 MB instead of 42 (the carry limit is 64 MiB).
strip --strip-debug -o "$OUT_SO" "$BUILD/src/gsplat/csrc$SUFFIX"
ls -la .whl "$OUT_SO"
du -sh .whl .gpu
