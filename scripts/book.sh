#!/usr/bin/env bash
# The docs book: installs mdBook if it is missing, builds docs/book into target/book and
# fails on any warning mdBook prints (a missing chapter, a broken include). Its links are
# checked by tests/docs.rs. Ends with "check passed: ..." as the other checks do.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v mdbook >/dev/null; then
    cargo install --locked mdbook --version "^0.4"
fi
log=$(mktemp)
trap 'rm -f "$log"' EXIT
mdbook build docs/book 2>&1 | tee "$log"
if grep -E "^\s*(\[?WARN|\[?ERROR|warning|error)" "$log"; then
    echo "mdbook reported problems" >&2
    exit 1
fi
test -s target/book/index.html
echo "check passed: mdbook build docs/book ($(find target/book -name '*.html' | wc -l) pages)"
