#!/usr/bin/env bash
# Every test of the project: the workspace's unit and end-to-end tests, then the core's
# cross-compilation for the embedded targets (with and without defmt), and the onboard checks
# (scripts/onboard.sh) and the Slurm check (scripts/slurm.sh). Installs the targets.
# Ends with one line counting everything that passed.
set -euo pipefail
cd "$(dirname "$0")/.."

targets=(thumbv7em-none-eabihf aarch64-unknown-none riscv32imafc-unknown-none-elf)
rustup target add "${targets[@]}"

log=$(mktemp)
trap 'rm -f "$log"' EXIT
cargo test --workspace 2>&1 | tee "$log"
passed=$(awk '/^test result: / { for (i = 1; i < NF; i++) if ($(i + 1) ~ /^passed/) n += $i } END { print n + 0 }' "$log")

builds=0
for target in "${targets[@]}"; do
    echo "cross-build: orbit-nerf-core for $target"
    cargo build -p orbit-nerf-core --release --target "$target"
    builds=$((builds + 1))
done
echo "cross-build: orbit-nerf-core for thumbv7em-none-eabihf with defmt"
cargo build -p orbit-nerf-core --release --target thumbv7em-none-eabihf --features defmt
builds=$((builds + 1))
# The library without its heavy optional parts (simulator, plots, Slurm): what an embedding
# team builds.
echo "build: orbit-nerf-host without default features"
cargo build -p orbit-nerf-host --no-default-features
builds=$((builds + 1))
# The library's example: a small simulated set trained and scored through orbit_nerf_host alone.
example_dir=$(mktemp -d)
cargo run --release --example train_eval -- "$example_dir" | tail -n 1
rm -rf "$example_dir"
builds=$((builds + 1))
# The docs book built with mdBook (its links are checked by tests/docs.rs).
./scripts/book.sh | tee "$log"
book=$(grep -c '^check passed:' "$log" || true)
builds=$((builds + book))
# The onboard checks: x86-64 = aarch64 training, Cortex-M = host rendering (under QEMU).
./scripts/onboard.sh | tee "$log"
onboard=$(grep -c '^check passed:' "$log" || true)
# The Slurm check: a sweep as a job array on a one-node Slurm = the same sweep run locally.
./scripts/slurm.sh | tee "$log"
slurm=$(grep -c '^check passed:' "$log" || true)
builds=$((builds + onboard + slurm))
# Tests and cross-builds together (a failure stops the script before this line).
echo "summary: $((passed + builds)) passed, 0 failed"
