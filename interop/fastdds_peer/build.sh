#!/bin/sh
# Builds the Fast DDS peer of the interop tests (Debian: libfastrtps-dev, libfastcdr-dev, g++).
# Output: target/fastdds_peer (next to the release binaries' directory, not in the tree).
set -eu
here="$(cd "$(dirname "$0")" && pwd)"
out="${1:-$here/../../target/fastdds_peer}"
mkdir -p "$(dirname "$out")"
g++ -std=c++17 -O1 -o "$out" "$here/peer.cpp" -lfastrtps -lfastcdr -lpthread
echo "$out"
