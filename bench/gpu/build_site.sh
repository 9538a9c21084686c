#!/usr/bin/env bash
# Build .gpu_site/site.tar.xz HERE (a machine with the package registries): the Python packages
# the device image lacks (it has torch, numpy, scipy, scikit-learn, matplotlib, tqdm, h5py, pyyaml,
# huggingface_hub, pillow, ...; /work/.library/device/KINDS.md), installed for the device's Python
# (3.12, x86-64) without their dependencies, as one xz archive (≈ 40 MB, mostly Meta-World's
# textures) so that it and the working tree stay under the device tool's 64 MiB.
#
#   bash bench/gpu/build_site.sh                                  # for the device (Python 3.12)
#   PYVER=3.11 OUT_DIR=/tmp/site311 bash bench/gpu/build_site.sh  # the same for this machine's Python
#
# Then: run(command="bash bench/gpu/check.sh", carry=[".gpu_site"], timeout_s=600).
set -euo pipefail
cd "$(dirname "$0")/../.."
PYVER=${PYVER:-3.12}
OUT_DIR=${OUT_DIR:-.gpu_site}
PY=${PY:-.venv/bin/python}
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
TAGS=(--only-binary=:all: --python-version "$PYVER" --implementation cp
      --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64
      --platform manylinux2014_x86_64 --platform manylinux1_x86_64)
# the versions this repository is tested with (.venv); hydra's antlr4 4.9.3 exists only as an sdist
PKGS=(torchrl==0.14.1 tensordict==0.14.3 hoptorch==0.1.4 pyvers==0.2.3 orjson==3.13.0 importlib_metadata==10.2.0
      gymnasium==1.4.0 farama-notifications==0.0.6 mujoco==3.3.0 glfw==2.11.0 PyOpenGL==3.1.10 metaworld==3.1.1
      hydra-core==1.3.8 omegaconf==2.3.1 diffusers==0.42.1)
"$PY" -m pip download -q --no-deps "${TAGS[@]}" -d "$WORK/wheels" "${PKGS[@]}" 2> >(grep -v "is ignored" >&2)
"$PY" -m pip wheel -q --no-deps -w "$WORK/wheels" antlr4-python3-runtime==4.9.3 2> >(grep -v "is ignored" >&2)
"$PY" -m pip install -q --no-deps --no-compile "${TAGS[@]}" --target "$WORK/site" "$WORK/wheels"/*.whl
rm -rf "$WORK/site/benchmarks" "$WORK/site/sota-implementations"  # torchrl's wheel ships these top-level extras
mkdir -p "$OUT_DIR"
tar -C "$WORK/site" -cf - . | xz -T2 -6 > "$OUT_DIR/site.tar.xz.tmp"
mv "$OUT_DIR/site.tar.xz.tmp" "$OUT_DIR/site.tar.xz"
ls -l "$OUT_DIR/site.tar.xz"
