#!/usr/bin/env bash
# The mapper firmware (`home` profile, all resources static) on whole CARMEN logs under
# `qemu-system-arm -icount shift=0`: instruction percentiles per section of the real-time and
# back-end work, counts, stack high-water and the real-time trajectory's relation error per log,
# then the firmware ELF's static footprint and allocator check by cloi-budget with the stack
# measured on the longest run (intel.clf). Takes about 15 minutes.
#
#   bench/firmware.sh [LOG ...]      (default: intel fr079 mit-csail)
set -euo pipefail
cd "$(dirname "$0")/.."
cargo run -q --release --locked -p cloi-qemu-tests --example firmware_map -- "$@"
echo
first=${1:-intel}
cargo run -q --locked -p cloi-budget -- \
  --elf armv7-target/firmware/target/armv7a-none-eabihf/release/cloi-mapper \
  --run-log "target/bench-firmware/$(basename "$first" .clf)/firmware.log" --stack-budget 65536
