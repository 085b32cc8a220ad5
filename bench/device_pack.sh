#!/usr/bin/env bash
# Packs what the device suite needs for a bare GPU machine that reaches no network (issue #21,
# item 5), in two parts that each fit one call's 64 MiB, and installs them there.
#
#   bash bench/device_pack.sh                 # here: builds .devpack/1 and .devpack/2 (~5 min)
#   bash bench/device_pack.sh --install 1     # there, call 1 (carry .devpack/1)
#   bash bench/device_pack.sh --install 2 && bash bench/device_suite.sh   # call 2, carry .devpack/2
#
# Part 1: Open3D without its GUI resources, ML ops and plotly viewer (the simulator and the map
# builder need only its geometry), the shared libraries it loads, the compiled wheels. Part 2:
# Taichi without its C API and examples, the pure-Python wheels, the real recordings
# (../shared/data: the benches and the tests read them). Both go to /tmp/site, the
# libraries to /tmp/gllibs; device_suite.sh uses them. /tmp survives between two calls only
# while the machine stays warm (30 s): make call 2 right after call 1. The device gets the
# working tree: commit or stash work in progress first.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=3.12  # the device image's python3
SITE=/tmp/site
LIBS=/tmp/gllibs

install_part() {
  mkdir -p "$SITE" "$LIBS"
  if [[ "$1" == 1 ]]; then
    tar -xJf .devpack/1/open3d.tar.xz -C "$SITE"
    # open3d.visualization imports plotly and dash at import time; neither is needed here
    printf 'def get_plotly_fig(*args, **kwargs):\n    raise ImportError("no plotly here")\n%s\n' \
      'draw_plotly = draw_plotly_server = get_plotly_fig' > "$SITE/open3d/visualization/draw_plotly.py"
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
      --target "$SITE" .devpack/1/wheels/*.whl
    local deb lib debs
    debs=$(mktemp -d)
    for deb in .devpack/1/debs/*.deb; do dpkg -x "$deb" "$debs"; done
    for lib in $(cat .devpack/1/libs.txt); do  # only those the machine lacks
      ldconfig -p | grep -q "$lib " && continue
      cp -L "$debs"/usr/lib/x86_64-linux-gnu/"$lib" "$LIBS"/ 2> /dev/null ||
        cp -L "$debs"/lib/x86_64-linux-gnu/"$lib" "$LIBS"/
    done
    LD_LIBRARY_PATH=$LIBS PYTHONPATH=$SITE python3 -c "import open3d" ||
      { echo "device_pack: open3d does not import here" >&2; exit 1; }
  else
    [[ -d "$SITE/open3d" ]] || { echo "device_pack: part 1 is not installed here (a new" \
      "machine? call 1 and call 2 must follow each other within 30 s)" >&2; exit 1; }
    tar -xJf .devpack/2/taichi.tar.xz -C "$SITE"
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
      --target "$SITE" .devpack/2/wheels/*.whl
    mkdir -p ../shared && cp -r .devpack/2/data ../shared/
  fi
  echo "device_pack: part $1 installed in $SITE"
}

download() {  # wheels for the device's python, exact versions of this environment
  local dest=$1; shift
  local specs=() name version
  for name in "$@"; do  # this environment's version; the newest where it lacks the package
    version=$(.venv/bin/python -m pip show "$name" 2> /dev/null | sed -n 's/^Version: //p')
    specs+=("$name${version:+==$version}")
  done
  .venv/bin/python -m pip download -q --no-deps --only-binary=:all: --python-version $PY \
    --implementation cp --platform manylinux_2_35_x86_64 --platform manylinux_2_28_x86_64 \
    --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 -d "$dest" "${specs[@]}"
}

slim() {  # a wheel unpacked, trimmed of $3..., tarred with xz into $2
  local tmp; tmp=$(mktemp -d)
  (cd "$tmp" && unzip -q "$1" && shift 2 && rm -rf $@)  # unquoted: the names are globs
  tar -C "$tmp" -cf - . | xz -9 -T0 > "$2"
  rm -rf "$tmp"
}

if [[ "${1:-}" == "--install" ]]; then install_part "${2:?part 1 or 2}"; exit; fi

rm -rf .devpack && mkdir -p .devpack/1/wheels .devpack/1/debs .devpack/2/wheels .devpack/2/data
wheels=$(mktemp -d)
download "$wheels" taichi
.venv/bin/python -m pip download -q --no-deps --only-binary=:all: --python-version $PY \
  --implementation cp --platform manylinux_2_35_x86_64 -d "$wheels" \
  "open3d-cpu==$(.venv/bin/python -m pip show open3d | sed -n 's/^Version: //p')"
slim "$wheels"/open3d_cpu-*.whl .devpack/1/open3d.tar.xz open3d/_ml3d open3d/examples \
  open3d/resources open3d/labextension open3d/nbextension open3d/open3d_tf_ops.so \
  open3d/open3d_torch_ops.so open3d/agent_skills 'open3d_cpu-*.data'
slim "$wheels"/taichi-*.whl .devpack/2/taichi.tar.xz taichi/_lib/c_api taichi/examples \
  taichi/assets 'taichi-*.data'
download .devpack/1/wheels zstandard apsw pydantic_core lz4 backports.zstd pygments rich
download .devpack/2/wheels foxglove-sdk dill mcap mcap-ros1-support mcap-ros2-support rosbags \
  ruamel.yaml pydantic annotated-types typing-inspection typer click markdown-it-py mdurl \
  shellingham typing_extensions small_gicp kiss-icp pydantic-settings python-dotenv natsort \
  pyquaternion
rm -rf "$wheels"
apt_opts=(-qq -oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64)
mkdir -p /tmp/amd64/partial && apt-get "${apt_opts[@]}" update
(cd .devpack/1/debs && apt-get "${apt_opts[@]}" download libegl1 libgl1 libglx0 \
  libglvnd0 libopengl0 libx11-6 libxcb1 libxau6 libxdmcp6 libbsd0 libmd0 libusb-1.0-0 libudev1 \
  libidn2-0 libunistring2 libgomp1)
echo libEGL.so.1 libGL.so.1 libGLX.so.0 libGLdispatch.so.0 libOpenGL.so.0 libX11.so.6 \
  libxcb.so.1 libXau.so.6 libXdmcp.so.6 libbsd.so.0 libmd.so.0 libusb-1.0.so.0 libudev.so.1 \
  libidn2.so.0 libunistring.so.2 libgomp.so.1 > .devpack/1/libs.txt
if [[ -d ../shared/data ]]; then cp -r ../shared/data/. .devpack/2/data/; fi  # ~12 MB
du -sh .devpack/1 .devpack/2
