#!/usr/bin/env bash
# Installs every Debian package lsqsurf needs to build, test and benchmark.
# Idempotent: packages already present are skipped, so a second run is quick.
# postgresql brings the server programs (initdb, pg_ctl) with which the tests start throwaway
# PostgreSQL servers on loopback for the shared job store; libpq-dev is its client library;
# pybind11-dev and the python3 packages build, install (a venv with pip, offline) and test the
# Python package (python/); libmicrohttpd-dev serves the job page (--http-listen) and
# libcpp-httplib-dev is the HTTP tests' client; chromium
# shows it in the browser test;
# libssl-dev hashes tokens and checks certificates; nginx-light is the gRPC balancer of the replica test; yamllint checks deploy/;
# iproute2 and util-linux (ip, unshare, runuser) make the namespaces of scripts/netns-replicas.sh;
# libembree-dev ray-casts the simulated sensors of bench/sensor_sim.cc.
# --with-poisson also installs Open3D (libopen3d-dev, large, and python3-open3d), needed only by
# the benchmark preset `bench-poisson` and bench/poisson_reference.py (the sensor bench's
# screened Poisson rows), which run screened Poisson side by side; --with-openvdb installs
# libopenvdb-dev, needed only by the preset `bench-openvdb` (the level-set reference of the
# front-tracking benchmarks); --with-vtk the VTK reference of the volume benchmark; --with-scipy
# SciPy and scikit-image, with which bench/exported_volume.py writes Delaunay meshes as other
# tools do and bench/thin_shapes.py the thin ground truths;
# --with-containers podman, debootstrap, podman-compose and the CNI dnsname plugin for
# scripts/container-base.sh, container-test.sh and compose-test.sh; --with-fuzz clang and its
# libFuzzer runtime for scripts/fuzz.sh. Any of them may be given.
set -euo pipefail

packages=(
  g++ cmake ninja-build pkg-config ccache clang-format python3
  libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev protobuf-compiler grpc-proto
  libeigen3-dev libnanoflann-dev libdraco-dev draco
  libspdlog-dev libfmt-dev
  libgtest-dev libgmock-dev libbenchmark-dev
  libssl-dev openssl libsqlite3-dev libpq-dev postgresql nginx-light yamllint prometheus-cpp-dev libabsl-dev libtbb-dev libcli11-dev zlib1g-dev libpugixml-dev liblzf-dev libembree-dev
  iproute2 util-linux
  libegl-dev libgl-dev libopengl-dev libegl-mesa0 libgl1-mesa-dri libstb-dev
  pybind11-dev python3-dev python3-numpy python3-pytest python3-venv python3-pip python3-wheel python3-setuptools
  libmicrohttpd-dev libcpp-httplib-dev chromium
)
# npm fetches the job page's libraries at build time (web/package-lock.json); a Node.js that
# brings its own npm (NodeSource's) is kept, since Debian's npm would replace it.
if ! command -v npm >/dev/null || ! command -v node >/dev/null; then packages+=(nodejs npm); fi
for option in "$@"; do
  case "$option" in
    --with-poisson) packages+=(libopen3d-dev python3-open3d) ;;  # bench-poisson preset; bench/poisson_reference.py
    --with-openvdb) packages+=(libopenvdb-dev libboost-dev) ;;  # OpenVDB's headers include Boost's.
    --with-vtk) packages+=(python3-vtk9 python3-numpy xvfb) ;;  # bench/vtk_volume_reference.py
    --with-containers) packages+=(podman runc debootstrap uidmap slirp4netns fuse-overlayfs podman-compose golang-github-containernetworking-plugin-dnsname) ;;  # scripts/container-*.sh, compose-test.sh
    --with-fuzz) packages+=(clang libclang-rt-dev) ;;  # scripts/fuzz.sh
    --with-scipy) packages+=(python3-scipy python3-numpy python3-skimage) ;;  # bench/exported_volume.py, thin_shapes.py, polytopes.py
    *) echo "install-deps: unknown option $option (--with-poisson, --with-openvdb, --with-vtk, --with-containers, --with-fuzz, --with-scipy)" >&2; exit 2 ;;
  esac
done

missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done

if ((${#missing[@]} == 0)); then
  echo "install-deps: all ${#packages[@]} packages present"
  exit 0
fi

echo "install-deps: installing ${missing[*]}"
sudo_cmd=()
if [[ $(id -u) -ne 0 ]]; then sudo_cmd=(sudo); fi
export DEBIAN_FRONTEND=noninteractive
"${sudo_cmd[@]}" apt-get update -qq
"${sudo_cmd[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}"
