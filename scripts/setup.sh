#!/usr/bin/env bash
# Set up smdinspect on a fresh Debian/Ubuntu machine:
#  1. the system libraries Open3D needs that a minimal machine lacks (libusb-1.0-0,
#     libgl1, libgomp1) and those VTK needs to render the 3D view offscreen without a
#     GPU or display (EGL with Mesa's software rasteriser: libegl1, libegl-mesa0,
#     libgl1-mesa-dri), and chromium, the headless browser the report tests render
#     report.html in, through apt-get, only those that are missing;
#  2. a virtual environment in .venv with smdinspect and its test extras installed.
# Safe to run again: it installs only what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

missing=()
for pkg in libusb-1.0-0 libgl1 libgomp1 libegl1 libegl-mesa0 libgl1-mesa-dri chromium; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
    echo "setup: installing Debian packages needed by open3d, vtk and the report tests: ${missing[*]}"
    sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}" >/dev/null
fi

if [ ! -x .venv/bin/python ]; then
    echo "setup: creating virtual environment .venv"
    python3 -m venv .venv
fi
echo "setup: installing smdinspect and its dependencies into .venv"
# smdinspect uses opencv-contrib (cv2 with ximgproc); the plain wheel ships the same cv2
# files, and the two must not be installed side by side.
if .venv/bin/python -m pip show -q opencv-python-headless >/dev/null 2>&1; then
    .venv/bin/python -m pip uninstall -q -y opencv-python-headless opencv-contrib-python-headless
fi
.venv/bin/python -m pip install -q --upgrade pip 2>&1 | grep -v "^WARNING: Location" || true
.venv/bin/python -m pip install -q -e '.[test]' 2>&1 | grep -v "^WARNING: Location" || true
.venv/bin/python -c "import open3d, cv2, trimesh, vtkmodules.vtkRenderingOpenGL2, smdinspect" \
    || { echo "setup: smdinspect does not import; see the errors above" >&2; exit 1; }
echo "setup: done (run commands with .venv/bin/smdinspect)"
