#!/usr/bin/env bash
# Onboard checks (README "Onboard"): installs what it needs, then
#  1. x86-64 = aarch64: the CLI, built for both and the aarch64 one run under qemu-aarch64,
#     trains lego at 16 px (scripts/onboard/train.toml: the tiny profile, 256 rays per step,
#     8 steps); the two checkpoints must have the same bytes.
#  2. Cortex-M = host: the firmware (QEMU mps2-an386, Cortex-M4F) renders one view from that
#     checkpoint's render pack in flash; the host renders the same view; same fingerprint.
# Prints both sides of each check, one `check passed:` line per check, and exits non-zero on
# the first difference.
set -euo pipefail
cd "$(dirname "$0")/.."

lego=${ONBOARD_LEGO:-../shared/data/nerf_synthetic/lego}
if [ ! -d "$lego" ]; then
    echo "onboard: skipping: $lego not found"
    exit 0
fi

packages=(qemu-user gcc-aarch64-linux-gnu libc6-dev-arm64-cross qemu-system-arm)
missing=()
for package in "${packages[@]}"; do
    dpkg -s "$package" >/dev/null 2>&1 || missing+=("$package")
done
if [ ${#missing[@]} -gt 0 ]; then
    sudo=$([ "$(id -u)" = 0 ] || echo sudo)
    $sudo apt-get update
    $sudo apt-get install -y --no-install-recommends "${missing[@]}"
fi
rustup target add aarch64-unknown-linux-gnu thumbv7em-none-eabihf

export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_LINKER=aarch64-linux-gnu-gcc
cargo build --release --bin orbit-nerf --example onboard_pack
cargo build --release --bin orbit-nerf --target aarch64-unknown-linux-gnu

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
train=(train --data "$lego" --size 16 --config scripts/onboard/train.toml --threads 1 --fit-steps 0)
target/release/orbit-nerf "${train[@]}" --out "$work/x86_64" >/dev/null
qemu-aarch64 -L /usr/aarch64-linux-gnu target/aarch64-unknown-linux-gnu/release/orbit-nerf \
    "${train[@]}" --out "$work/aarch64" >/dev/null
x86_hash=$(sha256sum <"$work/x86_64/checkpoint.onrf" | cut -d' ' -f1)
arm_hash=$(sha256sum <"$work/aarch64/checkpoint.onrf" | cut -d' ' -f1)
echo "checkpoint sha256, x86-64:  $x86_hash"
echo "checkpoint sha256, aarch64: $arm_hash"
if [ "$x86_hash" != "$arm_hash" ]; then
    echo "onboard: FAILED: x86-64 and aarch64 train different checkpoints" >&2
    exit 1
fi
echo "check passed: x86-64 and aarch64 train the same checkpoint bytes"

mkdir -p firmware/pack
host_line=$(target/release/examples/onboard_pack "$work/x86_64/checkpoint.onrf" firmware/pack/render.pack)
(cd firmware && cargo build --release)
firmware_out=$(cd firmware && timeout 600 cargo run --release 2>/dev/null)
echo "$host_line"
echo "$firmware_out"
host_hash=$(grep -o 'fnv1a 0x[0-9a-f]*' <<<"$host_line")
firmware_hash=$(grep -o 'fnv1a 0x[0-9a-f]*' <<<"$firmware_out" || true)
if [ -z "$firmware_hash" ] || [ "$host_hash" != "$firmware_hash" ]; then
    echo "onboard: FAILED: the Cortex-M render differs from the host's" >&2
    exit 1
fi
echo "check passed: the Cortex-M4F renders the same image bytes as the host"
