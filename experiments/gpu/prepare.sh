#!/usr/bin/env bash
# Prepares what the GPU run carries to the device machine (run here, from the repository root, once):
#   .whl/   wheels of the packages its image lacks (Python 3.12, manylinux x86-64)
#   .peer/  the peer harness and the upstream source it runs (both stay outside git)
# Usage: experiments/gpu/prepare.sh [PEER_HARNESS_DIR] [UPSTREAM_SRC_DIR]   (defaults ../shared/peer, /tmp/peer/src)
set -euo pipefail
cd "$(dirname "$0")/../.."
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo '/.whl/' >> .git/info/exclude
grep -qx '/.peer/' .git/info/exclude 2>/dev/null || echo '/.peer/' >> .git/info/exclude
PY=${PYTHON:-python3}
PLAT=(--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64
      --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform manylinux_2_24_x86_64
      --platform manylinux_2_31_x86_64 --platform manylinux_2_34_x86_64 --platform any)
# bridge_jax's dependencies missing from the device image, and theirs (the image has numpy, etils, protobuf,
# cloudpickle, absl-py, pillow, opencv, tqdm, psutil, flatbuffers, orbax, optax, flax, jax, pyyaml).
for pkg in grain array-record ml-collections tensorboardX portpicker; do
  "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp "${PLAT[@]}" \
      -d .whl "$pkg"
done
rm -rf .peer && mkdir -p .peer/harness
cp "${1:-../shared/peer}/harness.py" .peer/harness/
cp -r "${2:-/tmp/peer/src}" .peer/src
du -sh .whl .peer
echo "ready: carry .whl .peer (see experiments/gpu/README.md)"
