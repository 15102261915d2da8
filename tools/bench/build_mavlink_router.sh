#!/bin/sh
# Build mavlink-routerd (the peer of tools/bench/bench_mavlink_router.py) from source, outside
# the repository.  Prints the binary's path last; pass it as --mavlink-routerd.
#
#   tools/bench/build_mavlink_router.sh [BUILD_DIR] [SOURCE_DIR]
#
# BUILD_DIR   where everything goes (default ~/.cache/aurora-bench/mavlink-router): the source
#             clone, a venv with meson, the build; nothing is installed system-wide
# SOURCE_DIR  an existing checkout to build instead of cloning (its submodule
#             modules/mavlink_c_library_v2 must be there: git submodule update --init)
#
# Needs git, a C/C++ compiler, python3 (meson comes from PyPI into BUILD_DIR/venv) and ninja
# (apt install ninja-build; or pip install ninja, which the venv gets when there is none).
# The default buildtype of mavlink-router's meson.build (debugoptimized: -O2 -g) is kept:
# the build its users get.  Where systemd's pkg-config file is missing, the unit directory is
# given explicitly (it is only where the service file would be installed).
set -eu
BUILD_DIR=${1:-"$HOME/.cache/aurora-bench/mavlink-router"}
SOURCE_DIR=${2:-}
REPO=https://github.com/mavlink-router/mavlink-router
mkdir -p "$BUILD_DIR"
if [ -z "$SOURCE_DIR" ]; then
    SOURCE_DIR="$BUILD_DIR/src"
    if [ ! -d "$SOURCE_DIR/.git" ]; then
        git clone --recurse-submodules "$REPO" "$SOURCE_DIR"
    fi
fi
if [ ! -f "$SOURCE_DIR/modules/mavlink_c_library_v2/common/mavlink.h" ]; then
    (cd "$SOURCE_DIR" && git submodule update --init) || {
        echo "mavlink-router: the submodule modules/mavlink_c_library_v2 is missing;" >&2
        echo "clone https://github.com/mavlink/c_library_v2 there at the commit" >&2
        echo "'git -C $SOURCE_DIR ls-tree HEAD modules/' names" >&2
        exit 1
    }
fi
if [ ! -x "$BUILD_DIR/venv/bin/meson" ]; then
    python3 -m venv "$BUILD_DIR/venv"
    "$BUILD_DIR/venv/bin/pip" install --quiet meson
    command -v ninja >/dev/null 2>&1 || "$BUILD_DIR/venv/bin/pip" install --quiet ninja
fi
PATH="$BUILD_DIR/venv/bin:$PATH"
if [ ! -f "$BUILD_DIR/build/build.ninja" ]; then
    meson setup "$BUILD_DIR/build" "$SOURCE_DIR" -Dsystemdsystemunitdir=/tmp/unused
fi
ninja -C "$BUILD_DIR/build" src/mavlink-routerd >&2
echo "$BUILD_DIR/build/src/mavlink-routerd"
