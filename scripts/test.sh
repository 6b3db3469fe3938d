#!/usr/bin/env bash
# Every test of the project: the workspace's unit and end-to-end tests, then the core's
# cross-compilation for the embedded targets (with and without defmt). Installs the targets.
set -euo pipefail
cd "$(dirname "$0")/.."

targets=(thumbv7em-none-eabihf aarch64-unknown-none riscv32imafc-unknown-none-elf)
rustup target add "${targets[@]}"

cargo test --workspace

for target in "${targets[@]}"; do
    echo "cross-build: orbit-nerf-core for $target"
    cargo build -p orbit-nerf-core --release --target "$target"
done
echo "cross-build: orbit-nerf-core for thumbv7em-none-eabihf with defmt"
cargo build -p orbit-nerf-core --release --target thumbv7em-none-eabihf --features defmt
echo "cross-builds: 4 passed, 0 failed"
