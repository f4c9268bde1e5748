#!/usr/bin/env bash
# Optional step for the SAPIEN backend: a CPU Vulkan driver so SAPIEN's own renderer works without a GPU.
#
# Debian bookworm's Mesa 22 lavapipe lacks a Vulkan feature SAPIEN requires (descriptorBindingPartiallyBound);
# the Mesa 25 lavapipe of bookworm-backports has it. This script fetches that one package
# (mesa-vulkan-drivers) with apt-get and unpacks it into a private folder, and writes an ICD file there
# that names the driver by absolute path. It changes no installed package and no apt source of the system:
# apt-get runs with its own source list, lists and cache inside the folder (the mirror is the one the
# system's apt already uses for bookworm). The system's libdrm and libLLVM-15 satisfy the driver.
#
# The SAPIEN backend finds the folder by itself (<python prefix>/lavapipe, i.e. .venv/lavapipe, or
# $MSMEM_LAVAPIPE_DIR) and points VK_ICD_FILENAMES at it when that variable is unset.
#
# usage: simulators/msmem_sapien/setup_lavapipe.sh [DEST]     (DEST default: $MSMEM_LAVAPIPE_DIR or .venv/lavapipe)
# Idempotent: exits at once when DEST already holds a working driver. Exit 0 = installed, 1 = not possible here.
set -euo pipefail

root=$(cd "$(dirname "$0")/../.." && pwd)
dest=${1:-${MSMEM_LAVAPIPE_DIR:-$root/.venv/lavapipe}}
icd="$dest/lvp_icd.json"

find_driver() { find "$dest/root" -name libvulkan_lvp.so -print -quit 2>/dev/null || true; }

missing_libs() { ldd "$1" 2>/dev/null | awk '/not found/ {print $1}'; }

if [[ -f "$icd" && -n "$(find_driver)" && -z "$(missing_libs "$(find_driver)")" ]]; then
    echo "lavapipe already set up: $icd"
    exit 0
fi

fail() { echo "setup_lavapipe: $*" >&2; exit 1; }
command -v apt-get >/dev/null && command -v dpkg-deb >/dev/null || fail "needs Debian's apt-get and dpkg-deb"
# shellcheck disable=SC1091
. /etc/os-release
[[ "${VERSION_CODENAME:-}" == bookworm ]] || fail "written for Debian bookworm (this is ${PRETTY_NAME:-unknown})"

mirror=$(apt-get indextargets --format '$(REPO_URI)' "Codename: bookworm" "Identifier: Packages" 2>/dev/null | head -n1)
[[ -n "$mirror" ]] || fail "no bookworm source in the system's apt configuration (run apt-get update first?)"

apt_dir="$dest/apt"
mkdir -p "$apt_dir/lists/partial" "$apt_dir/cache/archives/partial" "$apt_dir/sources.list.d" "$dest/debs"
echo "deb [signed-by=/usr/share/keyrings/debian-archive-keyring.gpg] $mirror bookworm-backports main" \
    > "$apt_dir/sources.list"
apt_opts=(
    -o "Dir::Etc::SourceList=$apt_dir/sources.list"
    -o "Dir::Etc::SourceParts=$apt_dir/sources.list.d"
    -o "Dir::State::Lists=$apt_dir/lists"
    -o "Dir::Cache=$apt_dir/cache"
    -o "APT::Sandbox::User=$(id -un)"
    -o "Debug::NoLocking=1"
)
echo "fetching mesa-vulkan-drivers from bookworm-backports ($mirror)"
apt-get -qq "${apt_opts[@]}" update
(cd "$dest/debs" && rm -f mesa-vulkan-drivers_*.deb && apt-get -qq "${apt_opts[@]}" download mesa-vulkan-drivers/bookworm-backports)
deb=$(ls "$dest"/debs/mesa-vulkan-drivers_*.deb)
rm -rf "$dest/root"
dpkg-deb -x "$deb" "$dest/root"
driver=$(find_driver)
[[ -n "$driver" ]] || fail "libvulkan_lvp.so not found in $deb"

missing=$(missing_libs "$driver")
if [[ -n "$missing" ]]; then
    # The driver's other dependencies are ordinary bookworm packages (libllvm15, libxcb-*, ...): install the
    # absent ones from the system's own sources (--no-upgrade leaves installed packages as they are).
    # libdrm and libvulkan1 are left out: the system's libdrm2 suffices and SAPIEN bundles a Vulkan loader.
    deps=$(dpkg-deb -f "$deb" Depends | tr ',' '\n' | sed -E 's/[(|].*//; s/ //g' \
           | grep -v -E '^(libdrm2|libdrm-amdgpu1|libvulkan1|libc6|libgcc-s1|libstdc\+\+6)$' | sort -u)
    sudo=""
    [[ $(id -u) == 0 ]] || sudo=$(command -v sudo || true)
    if [[ $(id -u) == 0 || -n "$sudo" ]]; then
        echo "installing the driver's missing libraries ($(echo "$missing" | tr '\n' ' ')) from bookworm"
        $sudo apt-get update -qq
        # shellcheck disable=SC2086
        DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-upgrade --no-install-recommends $deps >/dev/null
        missing=$(missing_libs "$driver")
    fi
    [[ -z "$missing" ]] || fail "the driver needs system libraries that are missing: $(echo "$missing" | tr '\n' ' ')"
fi

version=$(dpkg-deb -f "$deb" Version)
shipped=$(find "$dest/root" -name 'lvp_icd*.json' -print -quit)
[[ -n "$shipped" ]] || fail "lvp_icd.json not found in $deb"
sed -E "s#\"library_path\": *\"[^\"]*\"#\"library_path\": \"$driver\"#" "$shipped" > "$icd"
# keep only lavapipe (the package also holds the GPU drivers and layers)
find "$dest/root" -type f ! -name libvulkan_lvp.so -delete
find "$dest/root" -type l -delete
rm -rf "$dest/debs"
rm -rf "$apt_dir"
echo "lavapipe $version set up: $icd"
echo "the SAPIEN backend uses it automatically (or: export VK_ICD_FILENAMES=$icd)"
