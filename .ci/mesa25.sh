#!/usr/bin/env bash
# Mesa 25's lavapipe (Vulkan on the CPU, with VK_KHR_ray_query) from Debian's backports,
# unpacked into a folder beside the system's Mesa, which stays installed: the tests then run
# on it through VK_ICD_FILENAMES, and the system's driver is still there for a run without it.
# Usage: .ci/mesa25.sh DIR   (prints the ICD file to point VK_ICD_FILENAMES at)
set -euo pipefail
mkdir -p "$1"
dir="$(cd "$1" && pwd)"
icd="$dir/lvp_icd.json"
lib="$dir/root/usr/lib/x86_64-linux-gnu/libvulkan_lvp.so"
if [ -f "$icd" ] && [ -f "$lib" ]; then
  echo "$icd"
  exit 0
fi
codename="$(. /etc/os-release && echo "${VERSION_CODENAME:-bookworm}")"
list=/etc/apt/sources.list.d/bvhtrace-backports.list
if ! grep -rqs "${codename}-backports" /etc/apt/sources.list /etc/apt/sources.list.d/; then
  echo "deb http://deb.debian.org/debian ${codename}-backports main" >"$list"
fi
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq >&2
mkdir -p "$dir"
# apt-get download writes into the current folder, as the _apt user when it can.
(cd "$dir" && rm -f mesa-vulkan-drivers_*.deb && chmod 0777 . &&
  apt-get download -qq -t "${codename}-backports" mesa-vulkan-drivers >&2)
dpkg-deb -x "$dir"/mesa-vulkan-drivers_*.deb "$dir/root"
[ -f "$lib" ] || { echo "mesa25: $lib not found in the package" >&2; exit 1; }
version="$(dpkg-deb -f "$dir"/mesa-vulkan-drivers_*.deb Version)"
case "$version" in
  2[5-9].*|[3-9]*) ;;
  *) echo "mesa25: ${codename}-backports has mesa-vulkan-drivers $version, not 25 or later" >&2; exit 1 ;;
esac
cat >"$icd" <<JSON
{
    "ICD": {
        "api_version": "1.4.305",
        "library_path": "$lib"
    },
    "file_format_version": "1.0.0"
}
JSON
echo "mesa25: lavapipe $version in $dir" >&2
echo "$icd"
