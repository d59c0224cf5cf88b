#!/usr/bin/env bash
# Idempotent set-up: .venv with the exact pins, the fix for the ROS wheels'
# hard-coded include paths, and a colcon build of zeus_msgs and zeus_ros into
# install/. A second run only re-runs the (incremental) colcon build.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
source scripts/ros_env.sh
venv="$ZEUS_VENV"
python_bin="${PYTHON:-python3.11}"

# A .venv that is a link to a missing directory (e.g. copied from another
# machine) would make `python -m venv` fail with "File exists".
if [ -L "$venv" ] && [ ! -e "$venv" ]; then
  echo "[setup] removing dangling link $venv"
  rm "$venv"
fi
if [ ! -x "$venv/bin/python" ]; then
  echo "[setup] creating $venv with $python_bin"
  "$python_bin" -m venv "$venv"
fi

want=$(sha256sum requirements.lock | cut -d' ' -f1)
stamp="$venv/.requirements.sha256"
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "[setup] installing requirements.lock (first run takes a few minutes)"
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check pip==24.3.1
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r requirements.lock
  echo "$want" > "$stamp"
fi

# Packages wanted for their data files only, installed without their dependencies
# (requirements-assets.lock: metaworld's Sawyer scene; its own pin would replace
# the mujoco that dm-control needs). Hash-checked; own stamp, so it also runs on
# a venv made before the file existed.
want_assets=$(sha256sum requirements-assets.lock | cut -d' ' -f1)
stamp_assets="$venv/.requirements-assets.sha256"
if [ "$(cat "$stamp_assets" 2>/dev/null)" != "$want_assets" ]; then
  echo "[setup] installing requirements-assets.lock (--no-deps)"
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps \
    --require-hashes -r requirements-assets.lock
  echo "$want_assets" > "$stamp_assets"
fi

# The wheels' CMake exports name the include dirs of the machine they were
# built on; point them at this venv's Python and numpy headers.
py_inc=$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
np_inc=$("$venv/bin/python" -c 'import numpy; print(numpy.get_include())')
grep -rlZ --include='*.cmake' '/opt/python/cp311-cp311' "$venv/share" 2>/dev/null \
  | xargs -0 -r sed -i \
      -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$np_inc#g" \
      -e "s#/opt/python/cp311-cp311/include/python3.11#$py_inc#g" || true

# The venv's share/ holds many package.xml files; keep colcon out of it.
touch "$venv/COLCON_IGNORE"

mkdir -p "$root/log"
echo "[setup] colcon build (zeus_msgs, zeus_ros)"
# PYTHONDONTWRITEBYTECODE (set in some shells and containers) makes setuptools'
# build_py and install_lib print "byte-compiling is disabled, skipping" on
# stderr at every build, which colcon reports as "1 package had stderr output".
# The install tree is built once and imported by every node: let it compile.
env -u PYTHONDONTWRITEBYTECODE "$venv/bin/colcon" --log-base "$root/log" build \
  --base-paths "$root" "$root/msg_defs" \
  --build-base "$root/build" --install-base "$root/install" \
  --event-handlers console_direct- summary+ \
  --cmake-args -DBUILD_TESTING=OFF -DPython3_EXECUTABLE="$venv/bin/python" \
  >"$root/log/colcon_build.txt" 2>&1 || { cat "$root/log/colcon_build.txt"; exit 1; }
tail -n 2 "$root/log/colcon_build.txt"
