# Source this file (bash): `source tools/env.sh` gives a shell where the built package is usable,
# whether it was built against /opt/ros/jazzy or against ROS 2 Jazzy from PyPI in .venv.
_uav_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
if [ -f /opt/ros/jazzy/setup.bash ] && [ ! -x "$_uav_root/.venv/bin/colcon" ]; then
  source /opt/ros/jazzy/setup.bash
else
  source "$_uav_root/.venv/bin/activate"
  export AMENT_PREFIX_PATH=$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}
fi
source "$_uav_root/install/setup.bash"
unset _uav_root
