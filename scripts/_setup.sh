# Sourced by demo.sh and test.sh: a virtual environment with the project (extras in $BONEMESH_EXTRAS), the
# system libraries MeshLab needs, and redis-server (the broker), installed with apt-get where missing.
# PYTHON: the interpreter the environment is made with (default python3; 3.11 to 3.13); VENV: its folder (default
# .venv), e.g. PYTHON=~/.pyenv/versions/3.12.1/bin/python VENV=.venv312 bash scripts/test.sh
# The versions come from constraints.txt (scripts/lock.py), as in the Docker image.
PYTHON="${PYTHON:-python3}"
VENV="${VENV:-.venv}"
export VENV
[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q -c constraints.txt -e ".${BONEMESH_EXTRAS:-}"
SUDO=""
if [ "$(id -u)" != 0 ] && command -v sudo >/dev/null; then SUDO=sudo; fi
need=""
# MeshLab (pymeshlab, the decimation) needs the system's OpenGL loader where a slim image lacks it
"$VENV/bin/python" -c "import pymeshlab" 2>/dev/null || need="$need libgl1 libglib2.0-0"
command -v redis-server >/dev/null || need="$need redis-server"
# the page's browser test drives Debian's headless Chromium; npm installs the page's pinned assets
command -v chromium >/dev/null && command -v chromedriver >/dev/null || need="$need chromium chromium-driver"
command -v npm >/dev/null || need="$need nodejs npm"
case "${BONEMESH_EXTRAS:-}" in *test*)  # the PACS tests run a real Orthanc; dciodvfy checks the Encapsulated STL
  { command -v Orthanc >/dev/null || [ -x /usr/sbin/Orthanc ]; } || need="$need orthanc orthanc-dicomweb"
  ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || need="$need postgresql"  # the database tests' server
  command -v dciodvfy >/dev/null || need="$need dicom3tools" ;;
esac
case "${BONEMESH_EXTRAS:-}" in *test*|*opencl*)  # the OpenCL backend (engine.backend) on the CPU: PoCL's driver
  ls /etc/OpenCL/vendors/*.icd >/dev/null 2>&1 || need="$need pocl-opencl-icd ocl-icd-libopencl1" ;;
esac
if [ -n "$need" ] && command -v apt-get >/dev/null; then
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $need >/dev/null 2>&1 || { $SUDO apt-get update -qq && $SUDO apt-get install -y -qq $need >/dev/null; }
fi
# the web page's scripts and decoders (package.json + package-lock.json), served by the API from node_modules
if command -v npm >/dev/null && ! [ node_modules/.package-lock.json -nt package-lock.json ]; then npm ci --no-audit --no-fund --ignore-scripts --loglevel=error >/dev/null; fi
